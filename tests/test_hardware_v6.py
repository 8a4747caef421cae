"""FTDCR v6, the second real robot: calibration from its pulls and the CLI on a folder without val.csv.

As for v4, the pattern labels of the pulls (``rep1_tendon<k>_id<servo>_pull``) are only the
independent answer of the calibration, which never reads them. data/ftdcr_v6 holds no val.csv by
design (a hidden hold-out): the CLI scores the models with the train-only proxies.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_hardware import assert_matches_committed_calibration, label_truth

from dacr_learn.hardware.calibration import calibrate
from dacr_learn.hardware.recording import load_recording
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "ftdcr_v6"
ROBOT = ROOT / "configs" / "robots" / "ftdcr_v6.yaml"
CALIBRATED = ROOT / "configs" / "robots" / "ftdcr_v6_calibrated.yaml"
pytestmark = pytest.mark.usefixtures("one_thread")


def test_ftdcr_v6_folder_has_no_validation_recording():
    assert sorted(p.name for p in DATA.iterdir()) == ["LICENSE", "README.md", "tendon_pull.csv", "train.csv"]


def test_calibration_recovers_the_servo_map_of_ftdcr_v6():
    spec = RobotSpec.from_yaml(ROBOT)
    pulls = load_recording(DATA / "tendon_pull.csv", spec)
    truth = label_truth(pulls)
    assert len(truth) == 9
    cal_spec, smap, report = calibrate(pulls, spec)
    assert {a.servo: (a.segment, a.joint) for a in smap.servos} == truth
    assert all(a.sign == 1 for a in smap.servos)
    for seg in report["segments"]:
        assert seg["angle_rms_deg"] < 8.0
    assert_matches_committed_calibration(cal_spec, smap, CALIBRATED)


@pytest.mark.slow
def test_cli_on_ftdcr_v6_without_val_chooses_a_default_on_train(tmp_path):
    from dacr_learn.hardware.study.cli import main

    out = tmp_path / "run"
    report = main(["--data", str(DATA), "--robot", str(CALIBRATED), "--out", str(out),
                   "--models", "cc", "--seeds", "0", "--proxies", "cv", "extrap"])
    results = json.loads((out / "results.json").read_text())
    assert report["rows"] == {"train": 1019, "val": 0} and results["val"] is None
    assert results["default_model"] == "cc"
    scores = results["selection"]["scores"]["cc"]
    assert set(scores["cv_folds"]) == {"single", "pair12", "pair13", "pair23"}
    assert 3.0 < scores["extrap"] < 20.0 and 3.0 < scores["cv"] < 20.0   # mm: a fit, not a failure
    assert not (out / "val_predictions.csv").exists()
