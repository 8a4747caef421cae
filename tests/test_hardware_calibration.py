"""Calibration from single-tendon pulls (dacr_learn.hardware.calibration) on FTDCR v4 and v6.

The pattern labels of the pulls (``rep1_tendon<k>_id<servo>_pull``) are only the independent answer: tendon k
belongs to segment k // 3, joint k % 3. The calibration itself never reads the labels; the result is the
committed calibrated robot YAML and servo map.
"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import torch
from conftest import assert_tree_close
from hardware_testkit import V4_CALIBRATED, V6_CALIBRATED, V6_DATA, V6_ROBOT

from dacr_learn.hardware.calibration import calibrate
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


def label_truth(rec) -> dict[str, tuple[int, int]]:
    """servo id → (segment, joint) from labels like rep1_tendon4_id2_pull (the independent answer)."""
    truth = {}
    for label in rec.labels:
        m = re.search(r"tendon(\d+)_id([^_]+)_", label)
        if m:
            k = int(m.group(1))
            truth[m.group(2)] = (k // 3, k % 3)
    return truth


# The calibration ends in least-squares fits whose last digits follow the CPU's float kernels (one
# ulp of an angle on another CPU was seen); sqrt(eps) ≈ 1.5e-8 (rad or m) is the precision such a
# fitted value can be asked for, and 1e4 times finer than any physical meaning of these numbers.
CALIBRATION_TOL = float(torch.finfo(torch.float64).eps) ** 0.5


def assert_matches_committed_calibration(cal_spec: RobotSpec, smap: ServoMap, calibrated: Path) -> None:
    """The committed calibrated YAML and servo map are this result: the same structure and servo ids,
    floats equal up to the rounding of another CPU's BLAS/LAPACK kernels (angles [rad], lengths [m])."""
    assert_tree_close(cal_spec.to_dict(), RobotSpec.from_yaml(calibrated).to_dict(), atol=CALIBRATION_TOL)
    committed = ServoMap.from_yaml(calibrated.parent / "servo_maps" / calibrated.name)
    assert_tree_close([dataclasses.asdict(a) for a in smap.servos], [dataclasses.asdict(a) for a in committed.servos],
                      atol=CALIBRATION_TOL)
    assert smap.slack_level == pytest.approx(committed.slack_level, rel=0, abs=CALIBRATION_TOL)


def test_calibration_recovers_the_servo_map_of_ftdcr_v4(v4_spec, v4_pulls):
    truth = label_truth(v4_pulls)
    assert len(truth) == 9
    cal_spec, smap, report = calibrate(v4_pulls, v4_spec)
    got = {a.servo: (a.segment, a.joint) for a in smap.servos}
    assert got == truth
    assert all(a.sign == 1 for a in smap.servos)
    assert report["slack_level_mm"] == pytest.approx(-9.99, abs=0.02)
    for seg, expected in zip(report["segments"], (-174.0, -145.0, -115.0), strict=True):
        assert seg["offset_deg"] == pytest.approx(expected, abs=3.0)
        assert seg["angle_rms_deg"] < 8.0
    assert_matches_committed_calibration(cal_spec, smap, V4_CALIBRATED)


def test_calibration_ignores_column_order_and_ids(v4_spec, v4_pulls):
    perm = [5, 0, 8, 2, 7, 1, 4, 6, 3]
    renamed = tuple(f"m{v4_pulls.servo_ids[p]}" for p in perm)
    shuffled = type(v4_pulls)(renamed, v4_pulls.servo[:, perm], v4_pulls.tip, v4_pulls.labels, v4_pulls.timestamp,
                              "shuffled")
    _, smap, _ = calibrate(shuffled, v4_spec)
    got = {a.servo[1:]: (a.segment, a.joint) for a in smap.servos}
    truth = label_truth(v4_pulls)
    for sid, (seg, _joint) in truth.items():          # same segments; joints up to a cyclic relabelling
        assert got[sid][0] == seg
    for seg in range(3):
        ids = [s for s in truth if truth[s][0] == seg]
        shift = {(got[s][1] - truth[s][1]) % 3 for s in ids}
        assert len(shift) == 1


def test_calibration_recovers_the_servo_map_of_ftdcr_v6():
    spec = RobotSpec.from_yaml(V6_ROBOT)
    pulls = load_recording(V6_DATA / "tendon_pull.csv", spec)
    truth = label_truth(pulls)
    assert len(truth) == 9
    cal_spec, smap, report = calibrate(pulls, spec)
    assert {a.servo: (a.segment, a.joint) for a in smap.servos} == truth
    assert all(a.sign == 1 for a in smap.servos)
    for seg in report["segments"]:
        assert seg["angle_rms_deg"] < 8.0
    assert_matches_committed_calibration(cal_spec, smap, V6_CALIBRATED)
