"""examples/track_trajectory.py: end to end with a small learned model, and the layout (Rerun blueprint) of the
track.rrd it writes: a named full-range plot per trajectory, one 3D view, opening at the end."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import ROOT, load_example
from rerun_testkit import FOLLOWING, WHOLE_RANGE, rrd_data, rrd_time_panel, rrd_views

from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


def test_tracking_example_runs_and_logs(learned_jacobian):
    """examples/track_trajectory.py end to end (coarse: 50 Hz, one 1-s lap) with the small model."""
    example = load_example("track_trajectory")
    d = learned_jacobian.run_dir
    summary = example.main(["--ckpt", str(d / "fk.ckpt"), "--out", str(d), "--rate", "50", "--period", "2",
                            "--laps", "1", "--joint-noise", "1e-5", "--radius-scale", "1.03"])
    for kind in ("circle", "figure8"):
        assert summary["results"][kind]["rms_pct"] <= 1.0
    assert (d / "track.rrd").stat().st_size > 0 and (d / "summary.json").is_file()


def _tracking_results(example, robot) -> dict[str, dict]:
    """What run_scenario returns, without a controller: the robot stays straight, the 'actual' tip is
    the reference plus a known offset (10 µm for the circle, 20 µm for the figure-8)."""
    from dacr_learn.clarke_space import ClarkeSpace

    spec, n = robot.spec, 40
    q = ClarkeSpace(spec).joints(torch.tensor(example._straight(spec), dtype=torch.float64))
    features = robot.features(q).numpy()
    results = {}
    for k, kind in enumerate(example.TRAJECTORIES, start=1):
        desired = example.trajectory(kind, spec, n, n // 2).numpy()
        results[kind] = {"desired": desired, "actual": desired + [0.0, 0.0, 1e-5 * k], "q": np.tile(q.numpy(), (n, 1)),
                         "features": np.repeat(features[None], n, axis=0), "step_us": np.full(n, 100.0)}
    return results


def test_tracking_recording_has_a_named_full_range_plot_per_trajectory_and_opens_at_the_end(tmp_path):
    example = load_example("track_trajectory")
    robot = example.SimulatedRobot(RobotSpec.from_yaml(ROOT / "configs" / "robots" / "type1.yaml"))
    path = tmp_path / "track.rrd"
    example.write_recording(path, robot, _tracking_results(example, robot), every=5)
    views = rrd_views(path).values()
    plots = sorted((v for v in views if v["class"] == "TimeSeries"), key=lambda v: v["origin"])
    # one plot per trajectory, each titled with its own name (not two plots called …/tracking_error_mm)
    assert [v["origin"] for v in plots] == ["metrics/circle", "metrics/figure8"]
    assert plots[0]["name"].startswith("circle: tracking error [mm]")
    assert plots[1]["name"].startswith("figure-8: tracking error [mm]")
    assert "RMS 0.0100" in plots[0]["name"] and "RMS 0.0200" in plots[1]["name"]
    assert all(v["ranges"] == [{"timeline": "step", "range": WHOLE_RANGE}] for v in plots)  # every step
    # one 3D view of the reference and actual paths and the robot, for both trajectories
    (scene,) = [v for v in views if v["class"] == "3D"]
    assert scene["origin"] == "scene" and not scene["hidden"]
    assert all(w in scene["name"] for w in ("reference", "actual", "robot", "circle", "figure-8"))
    data = rrd_data(path)
    assert {"/scene/circle/desired", "/scene/circle/actual", "/scene/figure8/robot/backbone",
            "/scene/figure8/title"} <= set(data)
    assert data["/metrics/figure8/tracking_error_mm"]["SeriesLines:names"][0][0].startswith("|actual − reference|")
    panel = rrd_time_panel(path)
    assert panel["TimePanelBlueprint:timeline"] == ["step"] and panel["TimePanelBlueprint:play_state"] == [FOLLOWING]


@pytest.mark.slow            # trains, exports and tracks (~20 s): with the slow tests (make test's balance)
def test_tracking_example_runs_on_a_compositional_three_segment_model(tmp_path):
    """The example on a compositional FK of the 3-segment coupled robot: its exported ``jacobian`` module
    (InferenceCompositionalJacobian) drives the resolved-rate controller (issue 22, item 3)."""
    import lightning.pytorch as pl

    from dacr_learn.datamodule import KinematicsDataModule
    from dacr_learn.training import FKModule

    robot = str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml")
    torch.manual_seed(0)
    module = FKModule(robot=robot, structure="compositional", rotation="twist", width=32, depth=2, lr=1e-2,
                      rot_weight=0.1)
    dm = KinematicsDataModule(robot=robot, n_train=8000, n_val=200, n_test=200, batch_size=256)
    trainer = pl.Trainer(max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", devices=1)
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(tmp_path / "fk.ckpt")
    summary = load_example("track_trajectory").main(
        ["--ckpt", str(tmp_path / "fk.ckpt"), "--out", str(tmp_path), "--rate", "100", "--period", "2", "--laps", "1"])
    assert summary["robot"] == RobotSpec.from_yaml(robot).name          # 100 Hz: rms 0.08 % / 0.11 % of L here
    for kind in ("circle", "figure8"):
        assert summary["results"][kind]["rms_pct"] <= 1.0
