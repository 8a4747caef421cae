"""IK of learned and hardware models and the CLI: the solver inverts whatever model it is given, and the verdict
is checked against that model's own prediction from the returned joints (not the solver's state)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import ROOT, TDCR3, random_features, reference_joint_vector

from dacr_learn import load_model
from dacr_learn.cli.ik import main
from dacr_learn.hardware.deploy import load_hardware_model
from dacr_learn.ik import LearnedFK, solve_ik
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.metrics import rotation_geodesic

F64 = torch.float64
FIXTURES = ROOT / "tests" / "data" / "main_87f426b"     # tiny trained models (read only)


def on_constraint_and_inside(spec, q: torch.Tensor) -> None:
    """Every joint vector (..., N) lies on the displacement constraint (NumPy geometry) inside the limits."""
    f = ClarkeEncoder(spec).to(F64)(q)
    for qi, fi in zip(q.reshape(-1, q.shape[-1]).numpy(), f.reshape(-1, *f.shape[-2:]).numpy(), strict=True):
        assert np.abs(reference_joint_vector(spec, fi) - qi).max() < 1e-9
        for k, seg in enumerate(spec.segments):
            assert np.hypot(fi[k, 0], fi[k, 1]) <= seg.radius * seg.bend * (1 + 1e-9)


@pytest.mark.parametrize("name", ["fk_compositional", "fk"])
def test_learned_fk_is_inverted_with_respect_to_the_network(name):
    net = load_model(FIXTURES / f"{name}.ckpt", dtype=F64)
    spec = net.spec
    q_true = ClarkeDecoder(spec).to(F64)(random_features(spec, (6,), 2))
    with torch.no_grad():
        target = net(q_true)                                   # reachable by the network by construction
    position_only = spec.num_actuated_features < 6              # the one-segment robot: 2 features
    goal = target[:, :3, 3] if position_only else target
    result = solve_ik(net, goal, n_solutions=3, position_only=position_only)
    assert result.success.any(1).all()
    with torch.no_grad():
        reached = net(result.q.reshape(-1, spec.num_joints)).view(6, 3, 4, 4)
    ok = result.success
    assert ((reached[..., :3, 3] - target[:, None, :3, 3]).norm(dim=-1)[ok] <= 1e-6).all()
    if not position_only:
        assert (rotation_geodesic(reached[..., :3, :3], target[:, None, :3, :3])[ok] <= 1e-5).all()
    on_constraint_and_inside(spec, result.q[ok])


def test_learned_fk_jacobian_equals_autodiff():
    """The folded Jacobian the solver uses for a trained FK model equals forward-mode autodiff of the network."""
    net = load_model(FIXTURES / "fk_compositional.ckpt", dtype=F64)
    model = LearnedFK(net)
    x = model.limits.sample(4, torch.Generator().manual_seed(0))
    pos, rot, jac = model.tip_and_jacobian(x)
    model.jacobian_module = None                                # the autodiff path
    pos2, rot2, jac2 = model.tip_and_jacobian(x)
    torch.testing.assert_close(pos, pos2, atol=1e-12, rtol=0)
    torch.testing.assert_close(jac, jac2, atol=1e-9, rtol=1e-9)


def test_hardware_model_servo_commands_inside_the_recorded_range():
    model = load_hardware_model(FIXTURES / "hardware_model.pt")
    commands = model.examples.to(F64)
    tips, _ = model.predict(commands[::8], static=True)        # reachable tips of recorded commands
    result = solve_ik(model, tips, n_solutions=2, position_only=True)
    assert result.success.any(1).all()
    q = result.q[result.success]
    assert (q >= commands.amin(0) - 1e-12).all() and (q <= commands.amax(0) + 1e-12).all()
    reached, _ = model.predict(q, static=True)
    rows = result.success.nonzero()[:, 0]
    assert ((reached - tips[rows]).norm(dim=-1) <= 1e-6).all()
    with pytest.raises(ValueError, match="position_only"):
        solve_ik(model, torch.eye(4, dtype=F64).expand(1, 4, 4))


def test_cli_writes_the_contract_and_checks_its_arguments(tmp_path, capsys):
    spec = TDCR3
    poses = forward_kinematics(spec, random_features(spec, (5,), 4))
    np.save(tmp_path / "T.npy", poses.numpy())
    np.save(tmp_path / "P.npy", poses[:, :3, 3].numpy())
    robot = str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml")
    out = tmp_path / "new" / "S.npz"
    main(["--robot", robot, "--targets", str(tmp_path / "T.npy"), "--out", str(out), "--solutions", "4"])
    s = np.load(out)
    assert s["q"].dtype == np.float64 and s["q"].shape == (5, 4, spec.num_joints)
    assert s["success"].dtype == np.bool_ and s["success"].shape == (5, 4) and s["success"].all()
    assert {"pos_err", "rot_err", "iterations", "distinct"} <= set(s.files)
    assert "solved 5/5 targets" in capsys.readouterr().out
    main(["--robot", robot, "--targets", str(tmp_path / "P.npy"), "--out", str(out), "--solutions", "2",
          "--position-only", "--tolerance", "1e-7", "1e-5"])
    s = np.load(out)
    assert s["q"].shape == (5, 2, spec.num_joints) and (s["pos_err"][s["success"]] <= 1e-7).all()
    with pytest.raises(ValueError, match="--targets .*expected \\(B, 4, 4\\) poses"):
        main(["--robot", robot, "--targets", str(tmp_path / "P.npy"), "--out", str(out)])
    with pytest.raises(ValueError, match="--out .*is a folder"):
        main(["--robot", robot, "--targets", str(tmp_path / "T.npy"), "--out", str(tmp_path)])
    with pytest.raises(FileNotFoundError, match="--targets"):
        main(["--robot", robot, "--targets", str(tmp_path / "missing.npy"), "--out", str(out)])


def test_cli_with_checkpoints_hardware_sigma_and_ik_seeds(tmp_path):
    model = load_hardware_model(FIXTURES / "hardware_model.pt")
    tips, _ = model.predict(model.examples[:3].to(F64), static=True)
    np.save(tmp_path / "tips.npy", tips.numpy())
    out = tmp_path / "hw.npz"
    main(["--ckpt", str(FIXTURES / "hardware_model.pt"), "--targets", str(tmp_path / "tips.npy"), "--out", str(out),
          "--solutions", "2", "--position-only"])
    s = np.load(out)
    assert s["success"].any(1).all() and s["sigma"].shape == (3, 2, 3) and (s["sigma"] > 0).all()
    ik_net = load_model(FIXTURES / "ik.ckpt", dtype=F64)       # an IK network seeds the analytic model
    poses = forward_kinematics(ik_net.spec, random_features(ik_net.spec, (3,), 5))
    np.save(tmp_path / "poses.npy", poses.numpy())
    main(["--ckpt", str(FIXTURES / "ik.ckpt"), "--targets", str(tmp_path / "poses.npy"), "--out", str(out),
          "--solutions", "2"])
    assert np.load(out)["success"].any(1).all()


def test_the_module_entry_point_reports_a_user_error_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dacr_learn.ik", "--robot", "nope.yaml", "--targets", "x.npy",
                           "--out", str(tmp_path / "s.npz")], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.strip().startswith("error: ") and len(proc.stderr.splitlines()) == 1
