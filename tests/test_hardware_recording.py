"""Recordings (dacr_learn.hardware.recording): the loader reads FTDCR v4's CSV files in SI units and refuses broken
ones naming the column or cell; a file that is not UTF-8 gives a ValueError naming it, a missing one a
FileNotFoundError."""
from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
import torch
from conftest import names
from hardware_testkit import V4_DATA, write_csv

from dacr_learn.hardware.recording import load_recording

pytestmark = pytest.mark.usefixtures("one_thread")


def test_recording_that_is_not_utf8_or_missing(tmp_path):
    from dacr_learn.hardware.recording import load_recording

    path = tmp_path / "rec.csv"
    path.write_bytes(b"timestamp,pattern_label\n\xff\xfe,\x00\n")
    with pytest.raises(ValueError, match=names(path, "expected a recording CSV", "UTF-8")):
        load_recording(path)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "missing.csv"))):
        load_recording(tmp_path / "missing.csv")


def read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(open(path)))
    return rows[0], rows[1:]


def test_loader_reads_the_recordings_in_si_units(v4_spec):
    rec = load_recording(V4_DATA / "train.csv", v4_spec)
    assert rec.servo.shape == (1620, 9) and rec.tip.shape == (1620, 3) and len(rec.labels) == 1620
    assert rec.servo.dtype == torch.float64
    assert rec.servo_ids == ("4", "3", "9", "5", "2", "8", "6", "1", "7")
    # README: about (-2, 8, 188) mm when straight; first row is straight.
    assert torch.allclose(rec.tip[0], torch.tensor([-2.085078e-3, 8.168024e-3, 187.961009e-3], dtype=torch.float64))
    assert rec.servo.min() > -0.0101 and rec.servo.max() < 0.02
    assert rec.labels[0] == "rep1_tendon0_id4_pull"
    assert bool((rec.timestamp[1:] > rec.timestamp[:-1]).all())


def _mutated(tmp_path: Path, name: str, fn) -> Path:
    header, rows = read_csv(V4_DATA / "val.csv")
    header, rows = fn(header, [list(r) for r in rows[:40]])
    return write_csv(tmp_path / name, header, rows)


@pytest.mark.parametrize("case, message", [
    ("missing_tip", "missing column 'tip_z'"),
    ("missing_label", "missing column 'pattern_label'"),
    ("no_servos", "no servo columns"),
    ("nan", "NaN"),
    ("text", "cannot parse"),
    ("metres_as_mm", "look too small"),
    ("mm_as_metres", "look too large"),
    ("unit_suffix", "unit mismatch"),
    ("servo_count", "servo columns but the robot"),
    ("time_backwards", "timestamps must increase"),
])
def test_loader_errors(tmp_path, v4_spec, case, message):
    def drop(col):
        def fn(h, rows):
            i = h.index(col)
            return h[:i] + h[i + 1:], [r[:i] + r[i + 1:] for r in rows]
        return fn

    def scale(factor, cols):
        def fn(h, rows):
            for r in rows:
                for i, name in enumerate(h):
                    if name.startswith(cols):
                        r[i] = str(float(r[i]) * factor)
            return h, rows
        return fn

    def set_cell(row, col, value):
        def fn(h, rows):
            rows[row][h.index(col)] = value
            return h, rows
        return fn

    cases = {
        "missing_tip": drop("tip_z"),
        "missing_label": drop("pattern_label"),
        "no_servos": lambda h, rows: (h[:2] + h[11:], [r[:2] + r[11:] for r in rows]),
        "nan": set_cell(5, "servo_9_mm", "nan"),
        "text": set_cell(3, "tip_x", "abc"),
        "metres_as_mm": scale(1e-3, ("servo", "tip")),
        "mm_as_metres": scale(1e3, ("tip",)),
        "unit_suffix": lambda h, rows: ([c.replace("servo_4_mm", "servo_4_m") for c in h], rows),
        "servo_count": drop("servo_7_mm"),
        "time_backwards": set_cell(10, "timestamp", "0.0"),
    }
    path = _mutated(tmp_path, f"{case}.csv", cases[case])
    with pytest.raises(ValueError, match=re.escape(message)):
        load_recording(path, v4_spec)


def test_loader_accepts_metres_when_declared(tmp_path, v4_spec):
    header, rows = read_csv(V4_DATA / "val.csv")
    header = [c.replace("_mm", "_m") for c in header]
    rows = [[r[0], r[1]] + [str(float(v) * 1e-3) for v in r[2:]] for r in rows[:30]]
    rec_m = load_recording(write_csv(tmp_path / "m.csv", header, rows), v4_spec, units="m")
    rec_mm = load_recording(V4_DATA / "val.csv", v4_spec)
    assert torch.allclose(rec_m.tip, rec_mm.tip[:30]) and torch.allclose(rec_m.servo, rec_mm.servo[:30])
