"""Whole-body resolved-rate control (dacr_learn.arm.control): converges, stays inside every limit (checked with the
NumPy URDF walk and the robot file's numbers), keeps the port, honours the URDF velocity limits, and the
decoupled scheme moves what it says it moves."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm, check_solution
from conftest import ROOT, TDCR3

from dacr_learn.arm import Composite, load_arm
from dacr_learn.arm.control import DecoupledController, Port, WholeBodyConfig, WholeBodyController

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
PANDA = ROOT / "configs" / "arms" / "panda.urdf"
MOUNT = np.load(ROOT / "configs" / "arms" / "panda_mount.npy")
READY = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.785], dtype=F64)      # flange pointing down


@pytest.fixture(scope="module")
def model():
    return Composite(load_arm(PANDA, "panda_link8"), torch.from_numpy(MOUNT), TDCR3)


def start(model: Composite, batch: int = 3) -> torch.Tensor:
    return model.joints(torch.cat([READY, model.robot.rest]).expand(batch, -1))


def nearby_targets(model: Composite, q: torch.Tensor, seed: int, size: float = 0.15) -> torch.Tensor:
    """Poses of admissible configurations a little away from q (reachable by construction)."""
    x = model.variables(q)
    step = size * model.limits.scale * (2 * torch.rand(x.shape, generator=torch.Generator().manual_seed(seed),
                                                       dtype=F64) - 1)
    return model.pose_of_variables(model.limits.project(x + step))


def assert_inside(model: Composite, q: torch.Tensor) -> None:
    ref = UrdfArm(PANDA, "panda_link8")
    for row in q.numpy():
        assert check_solution(ref, MOUNT, TDCR3, row, np.eye(4))[2]


@pytest.mark.parametrize("position_only", [False, True])
def test_whole_body_control_converges_inside_the_limits(model, position_only):
    q = start(model)
    target = nearby_targets(model, q, seed=1)
    target = target[:, :3, 3] if position_only else target
    ctrl = WholeBodyController(model, WholeBodyConfig(gain=0.5, max_step=0.2))
    ref = UrdfArm(PANDA, "panda_link8")
    for _ in range(40):
        q = ctrl.step(q, target)
        assert_inside(model, q)
    for b in range(q.shape[0]):
        pos, rot, _ = check_solution(ref, MOUNT, TDCR3, q[b].numpy(), target[b].numpy())
        assert pos < 1e-6 and rot < 1e-6


def test_the_port_keeps_the_robot_base_in_place(model):
    q = start(model, 2)
    centre = model.base_pose(READY[None])[0, :3, 3]
    port = Port(tuple(centre.tolist()), 0.002)
    target = nearby_targets(model, q, seed=2, size=0.05)
    free = WholeBodyController(model, WholeBodyConfig(max_step=0.2))
    held = WholeBodyController(model, WholeBodyConfig(max_step=0.2), port=port)
    q_free, q_held = q, q
    for _ in range(30):
        q_free, q_held = free.step(q_free, target), held.step(q_held, target)
    base = lambda qq: model.base_pose(qq[:, :7])[:, :3, 3]  # noqa: E731
    assert (base(q_held) - centre).norm(dim=-1).max() < port.radius
    assert (base(q_free) - centre).norm(dim=-1).max() > 5 * port.radius          # without it the base wanders
    assert model.check(q_held).position.sub(target[:, :3, 3]).norm(dim=-1).max() < 1e-3


def test_a_limit_holds_the_joint_and_the_rest_moves(model):
    """Joint 4 at its upper bound, a target that wants it further: it stays at the bound, no NaN, error falls."""
    x = model.variables(start(model, 1))
    x[0, 3] = model.limits.upper[3]
    q = model.joints(x)
    pushed = x.clone()
    pushed[0, 3] += 0.3                                              # beyond the URDF limit: not admissible
    target = model.pose_of_variables(pushed)
    ctrl = WholeBodyController(model, WholeBodyConfig(max_step=0.1))
    first = model.check(q).position.sub(target[:, :3, 3]).norm()
    for _ in range(15):
        q = ctrl.step(q, target)
        assert torch.isfinite(q).all() and q[0, 3] <= model.limits.upper[3]
        assert_inside(model, q)
    assert model.check(q).position.sub(target[:, :3, 3]).norm() < 0.5 * first


def test_velocity_limits_and_frozen_variables(model):
    q = start(model, 2)
    target = nearby_targets(model, q, seed=3, size=0.5)
    dt = 0.002
    ctrl = WholeBodyController(model, WholeBodyConfig(max_step=1.0, dt=dt))
    q1 = ctrl.step(q, target)
    velocity = torch.tensor(model.arm.chain.get_joint_velocity_limits()[1], dtype=F64)
    assert ((q1[:, :7] - q[:, :7]).abs() <= velocity * dt * (1 + 1e-12)).all()
    assert ((q1[:, :7] - q[:, :7]).abs() >= 0.999 * velocity * dt).any(-1).all()     # the fastest joint at its limit
    robot_only = WholeBodyController(model, moving=torch.arange(model.limits.num_variables) >= 7)
    q2 = robot_only.step(q, target)
    assert torch.equal(q2[:, :7], q[:, :7]) and not torch.equal(q2[:, 7:], q[:, 7:])


def test_decoupled_scheme_moves_the_arm_for_a_straight_robot_then_the_robot(model):
    q = start(model, 2)
    target = nearby_targets(model, q, seed=4)
    decoupled = DecoupledController(model, WholeBodyConfig(max_step=0.2))
    x = model.variables(q)
    arm_only = decoupled.arm.step_variables(x, target, rest=model.rest[7:].expand(2, -1))
    assert torch.equal(arm_only[:, 7:], x[:, 7:]) and not torch.equal(arm_only[:, :7], x[:, :7])
    q1 = decoupled.step(q, target)
    robot_step = decoupled.robot.step_variables(arm_only, target)
    assert torch.allclose(model.variables(q1), robot_step, rtol=0, atol=1e-15)


def test_bad_settings_are_named(model):
    with pytest.raises(ValueError, match="gain"):
        WholeBodyConfig(gain=0.0)
    with pytest.raises(ValueError, match="dt"):
        WholeBodyConfig(dt=-1.0)
    with pytest.raises(ValueError, match="port"):
        Port((0.0, 0.0), 0.01)
    with pytest.raises(ValueError, match="moving"):
        WholeBodyController(model, moving=torch.ones(3, dtype=torch.bool))
