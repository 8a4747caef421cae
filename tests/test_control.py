"""Resolved-rate controller: converges on static targets (analytic and learned Jacobian), never
commands joints outside the limits or off the displacement constraint, saturates correctly."""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol, spec_by_name

from dacr_learn.clarke_space import ClarkeSpace
from dacr_learn.deploy.control import ControllerConfig, ResolvedRateController, analytic_jacobian, scaled_dls_step
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.robot import RobotSpec

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
    assert all(residual(space, c) <= 1e-9 and bool(space.limits.inside(space.features(c))) for c in commands)


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
    d = space.limits.num_variables

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
            assert bool(space.limits.inside(space.features(q), tol=1e-9))


def test_saturate_clips_bend_length_and_twist():
    spec = spec_by_name("type3")                                            # bend 1.57, β ∈ [0.08, 0.12], α ∈ [-1, 1]
    space = ClarkeSpace(spec)
    f = torch.tensor([[0.03, 0.04, 0.2, -3.0], [0.001, 0.002, 0.1, 0.5]], dtype=F64)
    out = space.limits.project(f)
    rho = out[0, :2]
    assert torch.linalg.vector_norm(rho).item() == pytest.approx(1.57 * 0.008, rel=1e-12)
    assert torch.allclose(rho / rho.norm(), torch.tensor([0.6, 0.8], dtype=F64))     # radial clip keeps the plane
    assert out[0, 2].item() == 0.12 and out[0, 3].item() == -1.0
    assert torch.equal(out[1], f[1])                                   # inside the limits: unchanged
    assert space.limits.inside(out).all() and not space.limits.inside(f[0])


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


def test_converges_with_learned_jacobian(learned_jacobian):
    spec = RobotSpec.from_dict(learned_jacobian.metadata["robot"])
    space = ClarkeSpace(spec)
    target = tip(spec, space.joints(torch.tensor([0.005, 0.007, 0.095], dtype=F64)))
    ctrl = ResolvedRateController(spec, learned_jacobian)
    q, commands = run_closed_loop(ctrl, straight(space), target, steps=80)       # measured tip: closed loop
    assert torch.linalg.vector_norm(tip(spec, q) - target).item() <= 1e-6
    assert all(residual(space, c) <= 1e-9 and bool(space.limits.inside(space.features(c))) for c in commands)
    q, _ = run_closed_loop(ctrl, straight(space), target, steps=80, measured=False)  # the model's own FK
    model_tip = learned_jacobian(q)[0][:3, 3]
    assert torch.linalg.vector_norm(model_tip - target).item() <= 1e-5           # float32 model


# --------------------------------------------------------------------------------------------------
# The scaled damped-least-squares step of servo-space control (examples/control_hardware_model.py)
# --------------------------------------------------------------------------------------------------


def test_scaled_dls_step_solves_the_task_and_respects_the_step_limit():
    g = torch.Generator().manual_seed(0)
    jac = torch.randn(4, 3, 8, generator=g, dtype=torch.float64)
    task = 1e-3 * torch.randn(4, 3, generator=g, dtype=torch.float64)
    scale = 0.5 + torch.rand(8, generator=g, dtype=torch.float64)
    step = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3)       # undamped, unlimited: J·Δu = Δx
    assert ((jac @ step.unsqueeze(-1)).squeeze(-1) - task).abs().max() <= roundoff_tol(torch.float64, 1e-3, 1024)
    # minimum norm in z = u / s: Δz lies in the row space of J̃ = J·diag(s)
    dz, jt = step / scale, jac * scale
    proj = jt.mT @ torch.linalg.solve(jt @ jt.mT, jt @ dz.unsqueeze(-1))
    assert (proj.squeeze(-1) - dz).abs().max() <= roundoff_tol(torch.float64, float(dz.abs().max()), 1024)
    short = scaled_dls_step(jac, task, scale, damping=1e-2, max_step=1e-5)
    assert torch.allclose(torch.linalg.vector_norm(short / scale, dim=-1), torch.full((4,), 1e-5, dtype=torch.float64))


def test_scaled_dls_step_adds_the_secondary_step_in_the_null_space():
    g = torch.Generator().manual_seed(1)
    jac = torch.randn(3, 8, generator=g, dtype=torch.float64)
    task = 1e-3 * torch.randn(3, generator=g, dtype=torch.float64)
    scale = 0.5 + torch.rand(8, generator=g, dtype=torch.float64)
    z2 = 1e-2 * torch.randn(8, generator=g, dtype=torch.float64)
    plain = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3)
    both = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3, secondary=z2)
    tol = roundoff_tol(torch.float64, 1e-2, 1024)
    assert (jac @ both - task).abs().max() <= tol                        # the task is still solved exactly
    jt = jac * scale                                                     # the rest is z₂ minus its row-space part
    null_part = z2 - jt.mT @ torch.linalg.solve(jt @ jt.mT, jt @ z2)
    assert ((both - plain) / scale - null_part).abs().max() <= tol
    assert float(null_part.norm()) > 1e-3                                # not a vacuous check
    zero_column = jac.clone()
    zero_column[:, 2] = 0.0                                              # a slack tendon: J does not see it
    e2 = torch.zeros(8, dtype=torch.float64)
    e2[2] = 1e-2
    step = scaled_dls_step(zero_column, torch.zeros(3, dtype=torch.float64), scale, 1e-3, 1e3, secondary=e2)
    assert torch.allclose(step, e2 * scale, rtol=0, atol=tol)           # passes unchanged, even damped
    with pytest.raises(ValueError, match=r"secondary: expected shape \(8,\)"):
        scaled_dls_step(jac, task, scale, 0.0, 1.0, secondary=torch.zeros(7, dtype=torch.float64))
