"""Whole-body IK from the command line (python -m dacr_learn.ik --arm ARM.urdf --arm-tip LINK --mount M.npy): the
contract's shapes, every flagged solution re-checked with NumPy (tests/arm_reference.py), and bad arguments."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm, check_solution, random_urdf
from conftest import ROOT, TDCR3, spec_by_name

from dacr_learn.arm import Composite, load_arm
from dacr_learn.cli.ik import main

pytestmark = pytest.mark.usefixtures("one_thread")
PANDA = ROOT / "configs" / "arms" / "panda.urdf"
MOUNT = ROOT / "configs" / "arms" / "panda_mount.npy"
ROBOT = str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml")


def write_targets(tmp_path, model: Composite, n: int, seed: int) -> np.ndarray:
    poses = model.pose_of_variables(model.limits.sample(n, torch.Generator().manual_seed(seed))).numpy()
    np.save(tmp_path / "T.npy", poses)
    np.save(tmp_path / "P.npy", poses[:, :3, 3].copy())
    return poses


def arm_args(tmp_path, urdf=PANDA, tip="panda_link8", mount=MOUNT, robot=ROBOT) -> list[str]:
    return ["--robot", robot, "--arm", str(urdf), "--arm-tip", tip, "--mount", str(mount),
            "--out", str(tmp_path / "S.npz")]


def verify_file(out, urdf, tip, mount: np.ndarray, spec, targets: np.ndarray, k: int) -> dict:
    s = dict(np.load(out))
    n = len(UrdfArm(urdf, tip).names)
    assert s["q"].shape == (len(targets), k, n + spec.num_joints) and s["q"].dtype == np.float64
    assert s["success"].shape == (len(targets), k) and s["success"].dtype == bool
    ref = UrdfArm(urdf, tip)
    for b, j in zip(*np.nonzero(s["success"]), strict=True):
        pos, rot, inside = check_solution(ref, mount, spec, s["q"][b, j], targets[b])
        assert inside and pos <= 1e-6 and rot <= 1e-5, (b, j, pos, rot, inside)
    return s


def test_whole_body_cli_writes_the_contract(tmp_path, capsys):
    model = Composite(load_arm(PANDA, "panda_link8"), torch.from_numpy(np.load(MOUNT)), TDCR3)
    poses = write_targets(tmp_path, model, 6, seed=1)
    main(arm_args(tmp_path) + ["--targets", str(tmp_path / "T.npy"), "--solutions", "4"])
    s = verify_file(tmp_path / "S.npz", PANDA, "panda_link8", np.load(MOUNT), TDCR3, poses, 4)
    assert s["success"].all() and (s["distinct"].sum(1) >= 2).all()
    assert "panda.urdf (panda_link8) carrying" in capsys.readouterr().out
    main(arm_args(tmp_path) + ["--targets", str(tmp_path / "P.npy"), "--solutions", "3", "--position-only"])
    s = verify_file(tmp_path / "S.npz", PANDA, "panda_link8", np.load(MOUNT), TDCR3, poses[:, :3, 3], 3)
    assert s["success"].all() and (s["rot_err"] == 0).all()


def test_whole_body_cli_on_an_unseen_arm_and_robot(tmp_path):
    """A random URDF (prismatic / continuous joints, an encoding declaration) and a twisting robot."""
    text, tip = random_urdf(21, 5)
    urdf = tmp_path / "arm.urdf"
    urdf.write_text('<?xml version="1.0" encoding="utf-8"?>\n' + text, encoding="utf-8")
    mount = np.eye(4)
    mount[:3, 3] = [0.01, -0.02, 0.05]
    np.save(tmp_path / "M.npy", mount)
    spec = spec_by_name("twisting")
    robot = tmp_path / "robot.yaml"
    spec.to_yaml(robot)
    model = Composite(load_arm(urdf, tip), torch.from_numpy(mount), spec)
    poses = write_targets(tmp_path, model, 5, seed=2)
    q0 = model.joints(model.limits.sample(1, torch.Generator().manual_seed(3)))[0].numpy()
    np.save(tmp_path / "q0.npy", q0)
    main(arm_args(tmp_path, urdf, tip, tmp_path / "M.npy", str(robot))
         + ["--targets", str(tmp_path / "T.npy"), "--solutions", "4", "--q0", str(tmp_path / "q0.npy")])
    s = verify_file(tmp_path / "S.npz", urdf, tip, mount, spec, poses, 4)
    assert s["success"].any(1).all()


def test_whole_body_cli_names_bad_arguments(tmp_path):
    model = Composite(load_arm(PANDA, "panda_link8"), torch.from_numpy(np.load(MOUNT)), TDCR3)
    write_targets(tmp_path, model, 2, seed=4)
    targets = ["--targets", str(tmp_path / "T.npy")]
    with pytest.raises(ValueError, match="--arm needs --mount"):
        main(["--robot", ROBOT, "--arm", str(PANDA), "--arm-tip", "panda_link8", "--out", str(tmp_path / "S.npz")]
             + targets)
    with pytest.raises(ValueError, match="--arm is missing"):
        main(["--robot", ROBOT, "--mount", str(MOUNT), "--out", str(tmp_path / "S.npz")] + targets)
    with pytest.raises(ValueError, match="--arm-tip 'hand': no such link"):
        main(arm_args(tmp_path, tip="hand") + targets)
    np.save(tmp_path / "M32.npy", np.eye(4, dtype=np.float32))
    with pytest.raises(ValueError, match="--mount .*float64"):
        main(arm_args(tmp_path, mount=tmp_path / "M32.npy") + targets)
    np.save(tmp_path / "M3.npy", np.eye(3))
    with pytest.raises(ValueError, match="--mount .*\\(4, 4\\)"):
        main(arm_args(tmp_path, mount=tmp_path / "M3.npy") + targets)
    with pytest.raises(FileNotFoundError, match="--mount"):
        main(arm_args(tmp_path, mount=tmp_path / "none.npy") + targets)
    np.save(tmp_path / "q0.npy", np.zeros(TDCR3.num_joints))                 # the robot's joints only
    with pytest.raises(ValueError, match="q0.*19"):
        main(arm_args(tmp_path) + targets + ["--q0", str(tmp_path / "q0.npy")])
    assert not (tmp_path / "S.npz").exists()
