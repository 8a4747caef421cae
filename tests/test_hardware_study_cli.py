"""The hardware benchmark's command (dacr_learn.cli.hardware, python -m dacr_learn.hardware).

FTDCR v4 (results and visuals); FTDCR v6 (a folder without val.csv by design, a hidden hold-out: the models are
scored with the train-only proxies); the labelled synthetic robot of ``labelled_robot_dir`` (no val.csv: the
default model chosen on the proxies; ``--save`` bundles the final runs' models); and a synthetic second robot
(other servo ids, column order, joint count and routing) that checks that nothing depends on one robot's files.
"""
from __future__ import annotations

import io
import json
import math
import sys
from pathlib import Path

import pytest
import torch
from hardware_testkit import V4_CALIBRATED, V4_DATA, V6_CALIBRATED, V6_DATA, write_csv

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


TRUE_OFFSETS = (0.4, -1.1)


def _second_robot(tmp_path: Path) -> tuple[Path, RobotSpec]:
    nominal = {"name": "synthetic-2seg", "routing": "coupled", "segments": [
        {"type": "0", "length": 0.08, "radius": 0.005, "joints": 4, "offset": 0.0, "limits": {"bend": 0.8}},
        {"type": "0", "length": 0.07, "radius": 0.005, "joints": 4, "offset": 0.0, "limits": {"bend": 0.8}}]}
    path = tmp_path / "synthetic_2seg.yaml"
    RobotSpec.from_dict(nominal).to_yaml(path)
    true = {**nominal, "segments": [s | {"offset": o} for s, o in zip(nominal["segments"], TRUE_OFFSETS, strict=True)]}
    return path, RobotSpec.from_dict(true)


def _write_recording(path: Path, ids, cols, model, spec, x: torch.Tensor, labels) -> None:
    with torch.no_grad():
        tip = model(x) + 1e-4 * torch.randn(x.shape[0], 3, generator=torch.Generator().manual_seed(1),
                                            dtype=torch.float64)
    servo = x[:, cols]                                           # column c shows joint cols[c]
    rows = [[1000.0 + 0.5 * k, labels[k]] + [f"{v * 1e3:.5f}" for v in servo[k].tolist()]
            + [f"{v * 1e3:.5f}" for v in tip[k].tolist()] for k in range(x.shape[0])]
    write_csv(path, ["timestamp", "pattern_label"] + [f"servo_{i}_mm" for i in ids] + ["tip_x", "tip_y", "tip_z"], rows)


def test_second_robot_runs_through_the_same_command(tmp_path):
    from dacr_learn.cli.hardware import main

    robot_yaml, true_spec = _second_robot(tmp_path)
    ids = ["B7", "A2", "C1", "A9", "B3", "C5", "A4", "B1"]
    cols = [3, 6, 0, 5, 1, 7, 2, 4]                               # joint shown by each column
    model = CalibratedCC(true_spec, compliance=1e-7)
    data = tmp_path / "data"
    data.mkdir()
    ramp = torch.cat([torch.linspace(-2e-3, 3e-3, 8), torch.linspace(3e-3, -2e-3, 8)[1:]]).double()
    pulls = torch.full((8 * len(ramp), 8), -8e-3, dtype=torch.float64)
    for c in range(8):
        pulls[c * len(ramp):(c + 1) * len(ramp), cols[c]] = ramp
    _write_recording(data / "tendon_pull.csv", ids, cols, model, true_spec, pulls, ["pull"] * len(pulls))
    g = torch.Generator().manual_seed(2)
    for name, n in (("train.csv", 300), ("val.csv", 120)):
        feat = torch.zeros(n, 2, 4, dtype=torch.float64)
        feat[..., :2] = (torch.rand(n, 2, 2, generator=g, dtype=torch.float64) - 0.5) * 0.006
        feat[..., 2] = torch.tensor([0.08, 0.07], dtype=torch.float64)
        dec = ClarkeDecoder(true_spec)
        x = dec(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - dec(feat)
        _write_recording(data / name, ids, cols, model, true_spec, x, ["random"] * n)
    out = tmp_path / "run"
    report = main(["--data", str(data), "--robot", str(robot_yaml), "--out", str(out),
                   "--models", "linear_raw", "cc", "--seeds", "0", "--no-visuals"])
    smap = ServoMap.from_yaml(out / "servo_maps" / "calibrated_robot.yaml")
    cal = RobotSpec.from_yaml(out / "calibrated_robot.yaml")
    # Symmetric joints are only defined up to a cyclic relabelling: compare segment and angle.
    for a in smap.servos:
        true_joint = cols[ids.index(a.servo)]
        true_seg, true_i = divmod(true_joint, 4)
        assert a.segment == true_seg
        true_angle = true_spec.segments[true_seg].joint_angles[true_i]
        got_angle = cal.segments[a.segment].joint_angles[a.joint]
        assert math.remainder(got_angle - true_angle, 2 * math.pi) == pytest.approx(0.0, abs=math.radians(3))
    results = json.loads((out / "results.json").read_text())
    assert results["models"]["cc"]["val"]["rmse_mm"]["mean"] < 0.5
    assert report["best_clarke_model"] == "cc"


def test_cli_on_ftdcr_v4_writes_results_and_visuals(tmp_path):
    from dacr_learn.cli.hardware import main

    out = tmp_path / "run"
    report = main(["--data", str(V4_DATA), "--robot", str(V4_CALIBRATED), "--out", str(out),
                   "--models", "linear_raw", "cc", "--seeds", "0", "--no-proxies"])
    results = json.loads((out / "results.json").read_text())
    assert set(results["models"]) == {"linear_raw", "cc"} and results["default_model"] is None
    # README reference: linear least squares reaches 41 mm on val.csv
    assert results["models"]["linear_raw"]["val"]["rmse_mm"]["mean"] == pytest.approx(41.0, abs=1.0)
    assert results["models"]["cc"]["val"]["rmse_mm"]["mean"] < 9.0
    assert report["rows"] == {"train": 1620, "val": 443}
    assert (out / "val_tip_paths.png").stat().st_size > 10_000
    assert (out / "val_tip_paths.rrd").stat().st_size > 10_000


def test_ftdcr_v6_folder_has_no_validation_recording():
    assert sorted(p.name for p in V6_DATA.iterdir()) == ["LICENSE", "README.md", "tendon_pull.csv", "train.csv"]


@pytest.mark.slow
def test_cli_on_ftdcr_v6_without_val_chooses_a_default_on_train(tmp_path):
    from dacr_learn.cli.hardware import main

    out = tmp_path / "run"
    report = main(["--data", str(V6_DATA), "--robot", str(V6_CALIBRATED), "--out", str(out),
                   "--models", "cc", "--seeds", "0", "--proxies", "cv", "extrap"])
    results = json.loads((out / "results.json").read_text())
    assert report["rows"] == {"train": 1019, "val": 0} and results["val"] is None
    assert results["default_model"] == "cc"
    scores = results["selection"]["scores"]["cc"]
    assert set(scores["cv_folds"]) == {"single", "pair12", "pair13", "pair23"}
    assert 3.0 < scores["extrap"] < 20.0 and 3.0 < scores["cv"] < 20.0   # mm: a fit, not a failure
    assert not (out / "val_predictions.csv").exists()


# --------------------------------------------------------------------------------------------------
# The labelled synthetic robot: no val.csv
# --------------------------------------------------------------------------------------------------


class _Flushes(io.StringIO):
    """A stdout that keeps, at each flush, the text written so far."""

    def __init__(self):
        super().__init__()
        self.flushed: list[str] = []

    def flush(self):
        self.flushed.append(self.getvalue())
        super().flush()


LABELLED_ARGS = ("--models", "linear_raw", "cc", "--seeds", "0")


@pytest.fixture(scope="module")
def default_run(labelled_robot_dir, tmp_path_factory):
    """The command with its default proxies on the labelled robot: (report, out folder, its stdout as a _Flushes),
    shared read-only by the two tests below (one run of the benchmark: seconds)."""
    from dacr_learn.cli.hardware import main

    data, robot = labelled_robot_dir
    out = tmp_path_factory.mktemp("default_run") / "run"
    stdout = _Flushes()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "stdout", stdout)
        report = main(["--data", str(data), "--robot", str(robot), "--out", str(out), *LABELLED_ARGS])
    return report, out, stdout


def test_cli_without_val_records_the_default_model(default_run):
    report, out, stdout = default_run
    # progress: a start line, then a line per model as its proxies and as its final runs finish, each flushed as
    # it is printed (stdout redirected to a log file is block-buffered: unflushed, they would show at the end)
    lines = [line for line in stdout.getvalue().splitlines() if line.startswith("[")]
    assert lines[0].startswith("[start] 2 models") and len(lines) == 5, lines
    for stage in ("proxy", "final"):
        shown = [line for line in lines if line.startswith(f"[{stage} ")]
        assert [line.split()[1:3] for line in shown] == [["1/2]", "linear_raw"], ["2/2]", "cc"]], shown
    assert all(any(text.endswith(line + "\n") for text in stdout.flushed) for line in lines)
    results = json.loads((out / "results.json").read_text())
    assert results["default_model"] == report["default_model"] == "cc"
    assert results["selection"]["candidates"] == ["cc"] and results["val"] is None
    assert set(results["selection"]["scores"]) == {"linear_raw", "cc"}
    assert results["selection"]["proxies"] == ["extrap"]                   # the family CV only on request
    assert "cv" not in results["selection"]["scores"]["cc"] and "| – |" in (out / "results.md").read_text()
    assert "val" not in results["models"]["cc"] and results["models"]["cc"]["train"]["rmse_mm"]["mean"] < 0.3
    assert not (out / "val_predictions.csv").exists()
    assert "**`cc`** (default)" in (out / "results.md").read_text()
    selection = results["selection"]
    assert selection["rule"].startswith("one-standard-error") and "cc" in selection["reason"]
    assert selection["best_by_proxy"] == "cc" and selection["tied"] == ["cc"]
    assert set(selection["comparison"]) == {"cc"} and selection["comparison"]["cc"]["gap_mm"] == 0.0
    assert "extrap_std" in selection["scores"]["cc"] and selection["proxy_seeds"] == [0, 1, 2]
    assert f"{selection['scores']['cc']['extrap']:.2f} ± " in (out / "results.md").read_text()


def test_cli_computes_the_family_cv_on_request_and_keeps_the_default(labelled_robot_dir, default_run, tmp_path):
    from dacr_learn.cli.hardware import main, parse_args

    data, robot = labelled_robot_dir
    args = ["--data", str(data), "--robot", str(robot), *LABELLED_ARGS]
    full = main(args + ["--out", str(tmp_path / "full"), "--proxies", "cv", "extrap"])
    short = default_run[0]                                   # the same command without --proxies
    assert full["default_model"] == short["default_model"] == "cc" and full["selection"]["proxies"] == ["cv", "extrap"]
    for name in ("linear_raw", "cc"):
        f, s = full["selection"]["scores"][name], short["selection"]["scores"][name]
        assert set(f["cv_folds"]) == {"single", "pair12"} and f["extrap"] == pytest.approx(s["extrap"], rel=1e-9)
    with pytest.raises(SystemExit):
        parse_args(args + ["--out", str(tmp_path), "--proxies", "cv"])    # the default is chosen on extrap


@pytest.mark.slow                    # two spawned worker processes train the models: run once, in the first pass
def test_save_bundles_the_final_runs_models_instead_of_training_them_again(labelled_robot_dir, tmp_path,
                                                                            monkeypatch):
    """``--save`` (two worker processes): the saved ensemble is the benchmark's own final-run models, returned
    from the workers, and the σ model's held-out fits run in the workers too — nothing is trained in this
    process (fit_model / the held-out fold_predictions here raise). A member predicts like the same model trained
    here for its seed, the reported train RMSE per seed is the saved member's, and the σ model equals
    sigma_models_of computed here. One proxy seed (the selection needs a proxy, not three seeds of it): unlike
    ``--seeds`` it still leaves the σ model's held-out fits to their own worker tasks. Every fit, in the workers
    (which inherit the environment) and here, trains 100 steps (DACR_HARDWARE_STEPS): no check depends on the
    models' quality."""
    from dacr_learn.cli.hardware import main
    from dacr_learn.hardware.deploy.checkpoint import load_hardware_model
    from dacr_learn.hardware.metrics import tip_metrics
    from dacr_learn.hardware.study import benchmark, heldout

    data, robot = labelled_robot_dir
    out, save = tmp_path / "run", tmp_path / "model"
    fit_model = benchmark.fit_model
    monkeypatch.setenv("DACR_HARDWARE_STEPS", "100")

    def no_fit_here(*args):
        raise AssertionError(f"{args[0]} trained in the main process by --save (the default again, or its σ folds)")

    with monkeypatch.context() as patch:
        patch.setattr(benchmark, "fit_model", no_fit_here)      # the spawned workers import their own, unpatched
        patch.setattr(heldout, "fold_predictions", no_fit_here)
        report = main(["--data", str(data), "--robot", str(robot), "--out", str(out), "--models",
                       "cc_clarke_residual", "--seeds", "0", "1", "--proxy-seeds", "0", "--jobs", "2",
                       "--save", str(save)])
    assert report["default_model"] == "cc_clarke_residual"
    saved = load_hardware_model(save / "model.pt")
    setup = benchmark.load_setup(robot, data / "train.csv", None, tmp_path / "setup",
                       cc_variant=report["cc_fit"]["variant"]["chosen"])
    per_seed = report["models"]["cc_clarke_residual"]["train"]["rmse_mm"]["per_seed"]
    assert len(saved.members) == 2
    reference = fit_model("cc_clarke_residual", setup, 1).eval()               # one seed trained again here
    with torch.no_grad():
        got, want = [member(setup.train) for member in saved.members], reference(setup.train)
    assert torch.allclose(got[1], want, rtol=0, atol=1e-9)                     # [m]: the same fit
    assert float((got[0] - got[1]).abs().max()) > 1e-6                         # seed 0's member: another fit
    for seed in (0, 1):
        assert tip_metrics(got[seed], setup.train.tip)["rmse_mm"] == pytest.approx(per_seed[seed], abs=1e-3)
    calibration, sigma_model = heldout.sigma_models_of(heldout.held_out_folds(setup, "cc_clarke_residual", [0, 1],
                                                                              heldout.SIGMA_PROXIES))
    assert saved.sigma_model.terms == sigma_model.terms
    assert torch.allclose(saved.sigma_model.coefficients, sigma_model.coefficients, rtol=1e-6, atol=1e-12)
    assert float(saved.sigma_model.floor) == pytest.approx(float(sigma_model.floor), rel=1e-6)
    assert float(saved.sigma.scale) == pytest.approx(float(calibration.scale), rel=1e-6)
