"""python -m dacr_learn.plan ftl: the PLAN.npz contract (names, shapes, dtypes, s from 0 to the path's length), every
step's tip and limits re-checked with NumPy (tests/arm_reference.py), and bad arguments."""
from __future__ import annotations

import numpy as np
import pytest
from arm_reference import UrdfArm, check_solution
from conftest import ROOT

from dacr_learn.cli.plan import main
from dacr_learn.console import run_cli
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
ARMS = ROOT / "configs" / "arms"
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml"


def arc_path(tmp_path) -> np.ndarray:
    """An arc of radius 0.3 m from the origin, starting along +z, 0.12 m long (spacing 2 mm)."""
    angle = np.linspace(0.0, 0.12 / 0.3, 61)
    points = np.stack([0.3 * (1 - np.cos(angle)), np.zeros_like(angle), 0.3 * np.sin(angle)], -1)
    np.save(tmp_path / "P.npy", points)
    return points


def args(tmp_path, *extra: str) -> list[str]:
    return ["ftl", "--robot", str(ROBOT), "--arm", str(ARMS / "free_base.urdf"), "--arm-tip", "tool",
            "--mount", str(ARMS / "identity_mount.npy"), "--path", str(tmp_path / "P.npy"),
            "--out", str(tmp_path / "PLAN.npz"), *extra]


def test_the_plan_file_has_the_contracts_arrays(tmp_path):
    points = arc_path(tmp_path)
    main(args(tmp_path, "--steps", "9", "--rerun", str(tmp_path / "plan.rrd")))
    assert (tmp_path / "plan.rrd").stat().st_size > 0
    plan = dict(np.load(tmp_path / "PLAN.npz"))
    spec = RobotSpec.from_yaml(ROBOT)
    assert set(plan) == {"q", "s", "tip_err", "shape_dev", "shape_dev_max", "clearance", "success", "reason"}
    assert plan["q"].shape == (9, 6 + spec.num_joints) and plan["q"].dtype == np.float64
    for k in ("s", "tip_err", "shape_dev", "shape_dev_max", "clearance"):
        assert plan[k].shape == (9,) and plan[k].dtype == np.float64, k
    assert np.all(plan["clearance"] == np.inf)                                  # no scene
    assert plan["success"].shape == () and plan["success"].dtype == bool and bool(plan["success"])
    assert plan["reason"].shape == () and str(plan["reason"]) == ""
    length = np.linalg.norm(np.diff(points, axis=0), axis=1).sum()
    assert plan["s"][0] == 0 and np.all(np.diff(plan["s"]) >= 0) and abs(plan["s"][-1] - length) < 1e-12
    assert plan["tip_err"].max() <= 1e-6 * spec.total_length
    assert np.all(plan["shape_dev"] <= plan["shape_dev_max"] + 1e-15)
    ref = UrdfArm(ARMS / "free_base.urdf", "tool")
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    for q, s in zip(plan["q"], plan["s"], strict=True):           # the tip from the joints alone, in NumPy
        target = np.array([np.interp(s, arc, points[:, i]) for i in range(3)])
        pos, _, inside = check_solution(ref, np.eye(4), spec, q, target)
        assert inside and pos <= 1e-6 * spec.total_length


def test_a_failed_plan_is_written_with_its_reason(tmp_path, capsys):
    np.save(tmp_path / "P.npy", np.stack([np.full(50, 1.0), np.zeros(50), np.linspace(0.3, 0.4, 50)], -1))
    stage = ["ftl", "--robot", str(ROBOT), "--arm", str(ARMS / "insertion_stage.urdf"), "--arm-tip", "carriage",
             "--mount", str(ARMS / "identity_mount.npy"), "--path", str(tmp_path / "P.npy"),
             "--out", str(tmp_path / "PLAN.npz"), "--steps", "4"]
    main(stage)
    plan = np.load(tmp_path / "PLAN.npz")
    assert not bool(plan["success"]) and "cannot reach" in str(plan["reason"])
    assert "FAILED: the tip cannot reach" in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [
    (("--clearance", "0.001"), "--scene is missing"),
    (("--scene", "S.yaml", "--clearance", "-1"), "--clearance: expected a finite distance"),
    (("--steps", "1"), "--steps: expected >= 2"),
    (("--tolerance", "0"), "--tolerance"),
])
def test_bad_arguments_are_one_line_errors(tmp_path, capsys, extra, message):
    arc_path(tmp_path)
    assert run_cli(main, args(tmp_path, *extra)) == 2
    assert message in capsys.readouterr().err


def test_a_scene_adds_the_clearance_of_each_step(tmp_path, capsys):
    np.save(tmp_path / "P.npy", np.stack([np.zeros(51), np.zeros(51), np.linspace(0.3, 0.55, 51)], -1))
    (tmp_path / "S.yaml").write_text("obstacles:\n- {type: sphere, center: [0.0, 0.0, 0.5], radius: 0.01}\n")
    main(["ftl", "--robot", str(ROBOT), "--arm", str(ARMS / "insertion_stage.urdf"), "--arm-tip", "carriage",
          "--mount", str(ARMS / "identity_mount.npy"), "--path", str(tmp_path / "P.npy"),
          "--out", str(tmp_path / "PLAN.npz"), "--steps", "6", "--scene", str(tmp_path / "S.yaml"),
          "--clearance", "0.005"])
    plan = np.load(tmp_path / "PLAN.npz")
    assert plan["clearance"].shape == (6,) and plan["clearance"].dtype == np.float64
    assert not bool(plan["success"]) and str(plan["reason"]).startswith("clearance ")
    envelope = RobotSpec.from_yaml(ROBOT).segments[-1].body_radius          # step 0: the tip 0.19 m below the sphere
    assert abs(plan["clearance"][0] - (0.49 - 0.3 - envelope)) < 1e-8          # the sag of a nearly straight body
    assert "clearance min -0.018 m; FAILED: clearance" in capsys.readouterr().out


def test_bad_path_files_are_named(tmp_path, capsys):
    np.save(tmp_path / "P.npy", np.zeros((10, 2)))
    assert run_cli(main, args(tmp_path)) == 2
    err = capsys.readouterr().err
    assert "--path" in err and "(W, 3)" in err
    (tmp_path / "P.npy").unlink()
    assert run_cli(main, args(tmp_path)) == 2
    assert "no such file" in capsys.readouterr().err


def test_an_out_path_that_cannot_be_written_is_a_one_line_error_before_any_work(tmp_path, capsys):
    arc_path(tmp_path)
    (tmp_path / "file").write_text("")
    for out, message in ((tmp_path, "is a folder"), (tmp_path / "file" / "PLAN.npz", "is a file, not a folder")):
        assert run_cli(main, args(tmp_path, "--out", str(out))) == 2
        err = capsys.readouterr().err
        assert f"--out {out}: " in err and message in err
