"""Hardware recordings: CSV files of servo commands and motion-capture tip positions (docs/hardware.md).

One row per sample, time ordered: ``timestamp,pattern_label,servo_<id>_mm,...,servo_<id>_mm,tip_x,tip_y,tip_z``
(what each column holds: docs/hardware.md, "The recordings"; ``<id>`` without underscores or commas). Everything is
returned in metres as float64 tensors; checks raise ``ValueError`` naming the file and column.
"""
from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..checks import read_text
from ..robot import RobotSpec

UNIT_SCALE = {"mm": 1e-3, "m": 1.0}
TIP_COLUMNS = ("tip_x", "tip_y", "tip_z")
_SERVO_RE = re.compile(r"^servo_([^_,]+)_([a-z]+)$")


@dataclass(frozen=True)
class Recording:
    """One recording, SI units: servo_ids (hardware column order), servo (N, S) commanded displacements [m],
    tip (N, 3) [m] motion-capture frame, labels (N pattern labels), timestamp (N,) [s], source (the file)."""

    servo_ids: tuple[str, ...]
    servo: Tensor
    tip: Tensor
    labels: tuple[str, ...]
    timestamp: Tensor
    source: str

    def __len__(self) -> int:
        return self.servo.shape[0]

    def select(self, mask: Tensor) -> Recording:
        """Rows where the boolean ``mask`` (N,) is true, in their original order."""
        idx = torch.nonzero(mask, as_tuple=False).flatten().tolist()
        return Recording(self.servo_ids, self.servo[mask], self.tip[mask],
                         tuple(self.labels[i] for i in idx), self.timestamp[mask], self.source)


def _fail(source: str, msg: str) -> None:
    raise ValueError(f"{source}: {msg}")


def _servo_columns(header: list[str], source: str, units: str) -> list[tuple[int, str]]:
    """[(column index, servo id)] for every servo column; checks the unit suffixes."""
    cols = []
    for i, name in enumerate(header):
        m = _SERVO_RE.match(name.strip())
        if not m:
            continue
        if m.group(2) != units:
            _fail(source, f"column {name!r} is in {m.group(2)!r} but units={units!r} was requested "
                  "(unit mismatch; pass the matching units or convert the file)")
        cols.append((i, m.group(1)))
    if not cols:
        _fail(source, f"no servo columns: expected columns named servo_<id>_{units}, got {header}")
    ids = [c[1] for c in cols]
    if len(set(ids)) != len(ids):
        _fail(source, f"duplicate servo ids in columns: {ids}")
    return cols


def _column_index(header: list[str], name: str, source: str) -> int:
    stripped = [h.strip() for h in header]
    if name not in stripped:
        _fail(source, f"missing column {name!r}; columns are {header}")
    return stripped.index(name)


def _parse_numbers(rows: list[list[str]], cols: list[int], header: list[str], source: str) -> np.ndarray:
    out = np.empty((len(rows), len(cols)), dtype=np.float64)
    for r, row in enumerate(rows):
        if len(row) != len(header):
            _fail(source, f"row {r + 2} has {len(row)} fields, the header has {len(header)}")
        for c, col in enumerate(cols):
            try:
                out[r, c] = float(row[col])
            except ValueError:
                _fail(source, f"row {r + 2}, column {header[col]!r}: cannot parse {row[col]!r} as a number")
    bad = ~np.isfinite(out)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        _fail(source, f"{int(bad.sum())} NaN/inf values, first at row {r + 2}, column {header[cols[c]]!r}")
    return out


def _check_scale(servo: np.ndarray, tip: np.ndarray, spec: RobotSpec | None, units: str, source: str) -> None:
    """Reject values whose magnitude contradicts the declared unit (SI arrays in, metres)."""
    length = spec.total_length if spec is not None else None
    reach = np.linalg.norm(tip, axis=1)
    if length is not None:
        typical = float(np.median(reach))
        if typical < 0.02 * length:
            _fail(source, f"tip positions look too small for units={units!r}: median distance from the origin "
                  f"{typical:.3g} m for a {length:.3g} m robot (values in metres recorded as {units}?)")
        if typical > 50 * length:
            _fail(source, f"tip positions look too large for units={units!r}: median distance from the origin "
                  f"{typical:.3g} m for a {length:.3g} m robot (values in mm recorded as {units}?)")
        span = float(np.abs(servo).max())
        if span > length:
            _fail(source, f"servo displacements up to {span:.3g} m exceed the robot length {length:.3g} m "
                  f"(values in mm recorded as {units}?)")
    tip_motion = float(np.ptp(tip, axis=0).max()) if len(tip) > 1 else 0.0
    servo_motion = float(np.ptp(servo)) if len(servo) > 1 else 0.0
    if tip_motion > 1e-2 and servo_motion < 1e-5:
        _fail(source, f"the tip moves {tip_motion:.3g} m but the servo values span only {servo_motion:.3g} m "
              f"(servo values in metres recorded as {units}?)")


def read_rows(path: str | Path) -> tuple[list[str], list[list[str]]]:
    """Header and data rows of a CSV file; ValueError when it is empty."""
    source = str(path)
    text = read_text(path, "a recording CSV (header row, then one row per sample)")
    rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r]
    if not rows:
        _fail(source, "empty file (no header)")
    if len(rows) < 2:
        _fail(source, "no data rows")
    return rows[0], rows[1:]


def load_recording(path: str | Path, spec: RobotSpec | None = None, units: str = "mm") -> Recording:
    """Read a recording CSV (format of the module docstring) into SI tensors (float64).

    ``spec``: when given, the number of servo columns must equal its number of joint lengths and magnitudes are
    checked against its total length; ``units``: unit of the servo and tip columns, "mm" or "m". ValueError for
    missing columns, NaN/inf, bad numbers, time going backwards, a column unit other than ``units``, or magnitudes
    that do not fit the unit.
    """
    source = str(path)
    if units not in UNIT_SCALE:
        _fail(source, f"units: got {units!r}, expected one of {sorted(UNIT_SCALE)}")
    header, rows = read_rows(path)
    i_time = _column_index(header, "timestamp", source)
    i_label = _column_index(header, "pattern_label", source)
    i_tip = [_column_index(header, name, source) for name in TIP_COLUMNS]
    servo_cols = _servo_columns(header, source, units)
    if spec is not None and len(servo_cols) != spec.num_length_joints:
        _fail(source, f"{len(servo_cols)} servo columns but the robot {spec.name!r} has "
              f"{spec.num_length_joints} joints")
    numbers = _parse_numbers(rows, [i_time] + [c for c, _ in servo_cols] + i_tip, header, source)
    scale = UNIT_SCALE[units]
    t, servo, tip = numbers[:, 0], numbers[:, 1:-3] * scale, numbers[:, -3:] * scale
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        r = int(np.argmax(~(np.diff(t) > 0)))
        _fail(source, f"timestamps must increase; row {r + 3} is not after row {r + 2}")
    _check_scale(servo, tip, spec, units, source)
    as_t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    return Recording(tuple(i for _, i in servo_cols), as_t(servo), as_t(tip),
                     tuple(r[i_label] for r in rows), as_t(t), source)


def concatenate(recordings: list[Recording]) -> Recording:
    """Stack recordings with the same servo ids (row order kept; timestamps may restart)."""
    ids = recordings[0].servo_ids
    for r in recordings[1:]:
        if r.servo_ids != ids:
            raise ValueError(f"{r.source}: servo ids {r.servo_ids} differ from {ids} in {recordings[0].source}")
    cat = lambda name: torch.cat([getattr(r, name) for r in recordings])  # noqa: E731
    return Recording(ids, cat("servo"), cat("tip"), tuple(l for r in recordings for l in r.labels),
                     cat("timestamp"), "+".join(r.source for r in recordings))
