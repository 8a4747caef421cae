"""Resolved-rate controller: converges on static targets (analytic and learned Jacobian), never
commands joints outside the limits or off the displacement constraint, saturates correctly."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from conftest import roundoff_tol, spec_by_name

from dacr_learn import export as dexport
from dacr_learn.control import ClarkeSpace, ControllerConfig, ResolvedRateController, analytic_jacobian
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

ROOT = Path(__file__).resolve().parents[1]
TYPE1 = ROOT / "configs" / "robots" / "type1.yaml"
F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")




def straight(space: ClarkeSpace) -> torch.Tensor:
    """Joint vector of the straight robot at nominal length."""
    return space.joints(space.fold.e0)


def residual(space: ClarkeSpace, q: torch.Tensor) -> float:
    """‖q − dec(enc(q))‖ (float64): zero on the displacement constraint."""
    return torch.linalg.vector_norm(q - space.decoder(space.encoder(q)), dim=-1).max().item()


def run_closed_loop(ctrl: ResolvedRateController, q: torch.Tensor, target: torch.Tensor, steps: int,
                    measured: bool = True) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Drive the analytic CC robot to ``target``; returns the final q and every command."""
    commands = []
    for _ in range(steps):
        tip = forward_kinematics(ctrl.spec, ctrl.space.encoder(q))[..., :3, 3] if measured else None
        q = ctrl.step(q, target, measured=tip)
        commands.append(q)
    return q, commands


def tip(spec: RobotSpec, q: torch.Tensor) -> torch.Tensor:
    return forward_kinematics(spec, ClarkeSpace(spec).encoder(q))[..., :3, 3]


@pytest.mark.parametrize("robot", ["type1", "type3"])
def test_converges_on_static_target_with_analytic_jacobian(robot):
    spec = spec_by_name(robot)
    space = ClarkeSpace(spec)
    target_q = space.joints(torch.tensor([0.006, -0.004, 0.105] + ([0.3] if robot == "type3" else []), dtype=F64))
    target = tip(spec, target_q)
    ctrl = ResolvedRateController(spec, analytic_jacobian(spec))
    q, commands = run_closed_loop(ctrl, straight(space), target, steps=80)
    assert torch.linalg.vector_norm(tip(spec, q) - target).item() <= 1e-9
    assert all(residual(space, c) <= 1e-9 and bool(space.within_limits(space.features(c))) for c in commands)


def test_batched_step_matches_single_steps():
    spec = spec_by_name("type1")
    ctrl = ResolvedRateController(spec, analytic_jacobian(spec))
    q = straight(ctrl.space).expand(3, -1)
    targets = torch.tensor([[0.02, 0.0, 0.09], [0.0, -0.03, 0.085], [0.01, 0.01, 0.11]], dtype=F64)
    batched = ctrl.step(q, targets)
    single = torch.stack([ctrl.step(q[i], targets[i]) for i in range(3)])
    assert batched.shape == (3, 4)
    # a damped least-squares solve per sample vs batched: rounding differences only
    assert torch.allclose(batched, single, rtol=0, atol=roundoff_tol(F64, float(single.abs().max()), ulps=1024))


@pytest.mark.parametrize("robot", ["type1", "type3", "tdcr_3seg_coupled", "twisting"])
def test_commands_stay_within_limits_and_on_the_constraint(robot):
    """Unreachable targets and a wrong (random) Jacobian with big steps: saturation must hold."""
    spec = spec_by_name(robot)
    space = ClarkeSpace(spec)
    g = torch.Generator().manual_seed(0)
    d = space.scale.numel()

    def wrong_jacobian(q):
        pose = forward_kinematics(spec, space.encoder(q))
        return pose, torch.randn(*q.shape[:-1], 6, d, generator=g, dtype=F64), None

    for jacobian, max_step in ((analytic_jacobian(spec), 0.5), (wrong_jacobian, 2.0)):
        ctrl = ResolvedRateController(spec, jacobian, ControllerConfig(gain=1.0, max_step=max_step))
        q = straight(space)
        for _ in range(60):
            target = 0.3 * torch.randn(3, generator=g, dtype=F64)       # mostly far outside the workspace
            q = ctrl.step(q, target, feedforward=0.05 * torch.randn(3, generator=g, dtype=F64))
            assert residual(space, q) <= 1e-9
            assert bool(space.within_limits(space.features(q), tol=1e-9))


def test_saturate_clips_bend_length_and_twist():
    spec = spec_by_name("type3")                                            # bend 1.57, β ∈ [0.08, 0.12], α ∈ [-1, 1]
    space = ClarkeSpace(spec)
    f = torch.tensor([[0.03, 0.04, 0.2, -3.0], [0.001, 0.002, 0.1, 0.5]], dtype=F64)
    out = space.saturate(f)
    rho = out[0, :2]
    assert torch.linalg.vector_norm(rho).item() == pytest.approx(1.57 * 0.008, rel=1e-12)
    assert torch.allclose(rho / rho.norm(), torch.tensor([0.6, 0.8], dtype=F64))     # radial clip keeps the plane
    assert out[0, 2].item() == 0.12 and out[0, 3].item() == -1.0
    assert torch.equal(out[1], f[1])                                   # inside the limits: unchanged
    assert space.within_limits(out).all() and not space.within_limits(f[0])


def test_analytic_jacobian_matches_finite_differences():
    spec = spec_by_name("tdcr_3seg_coupled")
    space = ClarkeSpace(spec)
    f = space.fold.e0 + torch.tensor([0.002, -0.001, 0.001] * 3, dtype=F64)
    q = space.joints(f)
    pose, jac_f, jac_q = analytic_jacobian(spec)(q)
    h = 1e-7
    for j in range(f.numel()):
        step = torch.zeros_like(f)
        step[j] = h
        dp = (tip(spec, space.joints(f + step)) - tip(spec, space.joints(f - step))) / (2 * h)
        assert torch.allclose(dp, jac_f[:3, j], atol=1e-6)
    assert jac_q.shape == (6, spec.num_joints) and torch.allclose(pose, forward_kinematics(spec, space.encoder(q)))


def test_config_validation():
    for kwargs in ({"gain": 0.0}, {"gain": 1.5}, {"damping": -1.0}, {"max_step": 0.0}):
        with pytest.raises(ValueError, match=next(iter(kwargs))):
            ControllerConfig(**kwargs)


@pytest.fixture(scope="module")
def learned_jacobian(tmp_path_factory):
    """A small FK model trained for a few seconds, exported (torch.export program) and loaded."""
    d = tmp_path_factory.mktemp("learned")
    torch.manual_seed(0)
    module = FKModule(robot=str(TYPE1), width=32, depth=2, lr=1e-2, rot_weight=0.1)
    dm = KinematicsDataModule(robot=str(TYPE1), n_train=6000, n_val=200, n_test=200, batch_size=256)
    trainer = pl.Trainer(max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", devices=1)
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(d / "fk.ckpt")
    dexport.export_checkpoint(d / "fk.ckpt", d / "export", aoti=False)
    jacobian = dexport.load(d / "export", "jacobian")
    jacobian.run_dir = d                    # for the example test: checkpoint and export live here
    return jacobian


def test_converges_with_learned_jacobian(learned_jacobian):
    spec = RobotSpec.from_dict(learned_jacobian.metadata["robot"])
    space = ClarkeSpace(spec)
    target = tip(spec, space.joints(torch.tensor([0.005, 0.007, 0.095], dtype=F64)))
    ctrl = ResolvedRateController(spec, learned_jacobian)
    q, commands = run_closed_loop(ctrl, straight(space), target, steps=80)       # measured tip: closed loop
    assert torch.linalg.vector_norm(tip(spec, q) - target).item() <= 1e-6
    assert all(residual(space, c) <= 1e-9 and bool(space.within_limits(space.features(c))) for c in commands)
    q, _ = run_closed_loop(ctrl, straight(space), target, steps=80, measured=False)  # the model's own FK
    model_tip = learned_jacobian(q)[0][:3, 3]
    assert torch.linalg.vector_norm(model_tip - target).item() <= 1e-5           # float32 model


def test_tracking_example_runs_and_logs(learned_jacobian):
    """examples/track_trajectory.py end to end (coarse: 50 Hz, one 1-s lap) with the small model."""
    spec = importlib.util.spec_from_file_location("track_trajectory", ROOT / "examples" / "track_trajectory.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    d = learned_jacobian.run_dir
    summary = example.main(["--ckpt", str(d / "fk.ckpt"), "--out", str(d), "--rate", "50", "--period", "2",
                            "--laps", "1", "--joint-noise", "1e-5", "--radius-scale", "1.03"])
    for kind in ("circle", "figure8"):
        assert summary["results"][kind]["rms_pct"] <= 1.0
    assert (d / "track.rrd").stat().st_size > 0 and (d / "summary.json").is_file()
