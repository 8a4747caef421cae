"""The arm + continuum robot model (dacr_learn.arm) against independent references: a NumPy walk of the URDF
(tests/arm_reference.py), the classic arc for the robot, pytorch-kinematics' own Jacobian, torch.func.jacrev
in float64; and whole-body IK whose every flagged solution is re-checked with that NumPy code."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm, check_solution, random_urdf
from conftest import ROOT, TDCR3, spec_by_name
from hypothesis import given, settings
from hypothesis import strategies as st

from dacr_learn.arm import Composite, load_arm
from dacr_learn.arm.seeds import PoseBank
from dacr_learn.ik import ConstantCurvature, IKOptions, solve_ik
from dacr_learn.ik.adapters import Check, SolverModel
from dacr_learn.lie import twist_jacobian

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
PANDA = ROOT / "configs" / "arms" / "panda.urdf"
MOUNT = np.load(ROOT / "configs" / "arms" / "panda_mount.npy")
POS_TOL, ROT_TOL = 1e-6, 1e-5


@pytest.fixture(scope="module")
def panda():
    return load_arm(PANDA, "panda_link8")


@pytest.fixture(scope="module")
def whole(panda):
    return Composite(panda, torch.from_numpy(MOUNT), TDCR3)


def random_mount(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    m = np.eye(4)
    m[:3, :3] = q * np.sign(np.linalg.det(q))
    m[:3, 3] = rng.uniform(-0.1, 0.1, 3)
    return m


def jacrev_twist(model: Composite, x: torch.Tensor) -> torch.Tensor:
    """The tip twist Jacobian (B, 6, n + D) of the differentiable FK by reverse-mode autodiff (torch.func)."""
    pose = model.pose_of_variables(x)
    dpose = torch.stack([torch.func.jacrev(lambda v: model.pose_of_variables(v[None])[0])(xi) for xi in x])
    return twist_jacobian(pose, dpose)


# --------------------------------------------------------------------------------------------------
# The arm: the URDF's geometry, joints and limits
# --------------------------------------------------------------------------------------------------


def test_panda_chain_is_the_urdf_to_round_off(panda):
    ref = UrdfArm(PANDA, "panda_link8")
    assert panda.joint_names == tuple(ref.names) == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert torch.equal(panda.limits.lower, torch.from_numpy(ref.lower))
    assert torch.equal(panda.limits.upper, torch.from_numpy(ref.upper))
    theta = panda.limits.sample(20, torch.Generator().manual_seed(0))
    poses = panda.tip_pose(theta).numpy()
    worst = max(np.abs(poses[i] - ref.tip_pose(theta[i].numpy())).max() for i in range(20))
    assert worst < 1e-13                     # pytorch-kinematics alone parses origins in float32: ~2e-8 m off


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), movable=st.integers(1, 6))
def test_any_urdf_chain_matches_numpy(seed, movable):
    """Random arms: revolute, continuous and prismatic joints, fixed joints between them, random origins and
    non-unit axes (some missing: the URDF default axis (1, 0, 0)), a side branch off the chain."""
    text, tip = random_urdf(seed, movable)
    arm, ref = load_arm(text, tip), UrdfArm(text, tip)
    assert arm.joint_names == tuple(ref.names)
    finite = np.isfinite(ref.lower)
    assert np.array_equal(arm.limits.lower.numpy()[finite], ref.lower[finite])
    assert np.all(arm.limits.lower.numpy()[~finite] == -2 * math.pi)          # continuous: the ±2π box
    theta = arm.limits.sample(8, torch.Generator().manual_seed(seed))
    poses = arm.tip_pose(theta).numpy()
    for i in range(8):
        np.testing.assert_allclose(poses[i], ref.tip_pose(theta[i].numpy()), rtol=0, atol=1e-12)


def test_bad_arms_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="--arm"):
        load_arm(tmp_path / "missing.urdf", "tip")
    with pytest.raises(ValueError, match="no such link.*panda_link8"):
        load_arm(PANDA, "flange")
    (tmp_path / "bad.urdf").write_text("<robot name='x'><link name='a'/><joint name='j'></robot>")
    with pytest.raises(ValueError, match="not a URDF"):
        load_arm(tmp_path / "bad.urdf", "a")
    mimic = ('<robot name="m"><link name="a"/><link name="b"/><link name="c"/>'
             '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
             '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="j1"/></joint></robot>')
    with pytest.raises(ValueError, match="mimic.*j2"):
        load_arm(mimic, "c")
    with pytest.raises(ValueError, match="empty range"):
        load_arm(mimic.replace('lower="-1" upper="1"', 'lower="0.5" upper="0.5"', 1), "b")
    with pytest.raises(ValueError, match="no movable joint"):
        load_arm(PANDA, "panda_link0")


# --------------------------------------------------------------------------------------------------
# The composite: FK, Jacobian, check
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "twisting"])
def test_whole_body_fk_matches_the_independent_chain(panda, robot):
    spec, mount = spec_by_name(robot), random_mount(3)
    model = Composite(panda, torch.from_numpy(mount), spec)
    x = model.limits.sample(12, torch.Generator().manual_seed(1))
    q = model.joints(x)
    ref = UrdfArm(PANDA, "panda_link8")
    pose, check = model.pose_of_variables(x), model.check(q)
    position, rotation, _ = model.tip_and_jacobian(x)
    for i in range(12):
        target = pose[i].numpy()
        assert check_solution(ref, mount, spec, q[i].numpy(), target)[:2] < (1e-12, 1e-12)
    assert torch.allclose(check.position, position, rtol=0, atol=1e-13)
    assert torch.allclose(check.rotation, rotation, rtol=0, atol=1e-13)
    assert check.inside.all() and check.constraint.max() < 1e-13
    assert torch.allclose(model.forward_kinematics(q), pose, rtol=0, atol=1e-13)


@pytest.mark.parametrize(("arm", "robot"), [("panda", "tdcr_3seg_coupled"), ("random", "twisting"),
                                             ("random", "hetero_4seg_types")])
def test_whole_body_jacobian_equals_jacrev_and_pytorch_kinematics(panda, arm, robot):
    chain = panda if arm == "panda" else load_arm(*random_urdf(7, 6))
    model = Composite(chain, torch.from_numpy(random_mount(5)), spec_by_name(robot))
    x = model.limits.sample(6, torch.Generator().manual_seed(2))
    position, _, jac = model.tip_and_jacobian(x)
    assert jac.shape == (6, 6, model.limits.num_variables) and jac.dtype == F64
    assert (jac - jacrev_twist(model, x)).abs().max() <= 1e-10
    theta = x[:, :model.num_arm]
    flange = chain.tip_pose(theta)                              # the tip point in the tip link's frame
    local = (torch.linalg.inv(flange) @ torch.cat([position, torch.ones(6, 1, dtype=F64)], 1).unsqueeze(-1))
    reference = chain.chain.jacobian(theta, locations=local[:, :3, 0])
    assert (jac[:, :, :model.num_arm] - reference).abs().max() <= 1e-10


def test_the_variables_and_limits_stack_arm_then_robot(whole, panda):
    n, robot = panda.num_joints, ConstantCurvature(TDCR3)
    assert whole.num_arm == n and whole.num_joints == n + TDCR3.num_joints
    assert whole.limits.names[:n] == tuple(f"arm.panda_joint{i}" for i in range(1, 8))
    assert torch.equal(whole.limits.disks, robot.limits.disks + n)
    assert torch.equal(whole.rest[:n], (panda.limits.lower + panda.limits.upper) / 2)
    q = whole.joints(whole.limits.sample(5, torch.Generator().manual_seed(4)))
    assert torch.allclose(whole.joints(whole.variables(q)), q, rtol=0, atol=1e-15)
    outside = q.clone()
    outside[0, 3] = panda.limits.upper[3] + 1e-6                                   # joint 4 past its URDF limit
    assert whole.check(outside).inside.tolist() == [False, True, True, True, True]


def test_bad_mounts_and_homes_are_named(panda):
    with pytest.raises(ValueError, match="mount.*\\(4, 4\\)"):
        Composite(panda, torch.eye(3, dtype=F64), TDCR3)
    skew = torch.eye(4, dtype=F64)
    skew[0, 1] = 0.1
    with pytest.raises(ValueError, match="mount.*rotation"):
        Composite(panda, skew, TDCR3)
    with pytest.raises(ValueError, match="mount.*NaN"):
        Composite(panda, torch.full((4, 4), math.nan, dtype=F64), TDCR3)
    with pytest.raises(ValueError, match="home"):
        Composite(panda, torch.eye(4, dtype=F64), TDCR3, home=torch.zeros(7, dtype=F64))   # joint 4 ≤ −0.0698


# --------------------------------------------------------------------------------------------------
# Whole-body IK
# --------------------------------------------------------------------------------------------------


def assert_every_flagged_solution_verifies(model: Composite, spec, mount, result, target) -> None:
    ref = UrdfArm(PANDA, "panda_link8")
    for b, k in result.success.nonzero().tolist():
        pos, rot, inside = check_solution(ref, mount, spec, result.q[b, k].numpy(), target[b].numpy())
        assert inside and pos <= POS_TOL and rot <= ROT_TOL, (b, k, pos, rot, inside)


@pytest.mark.parametrize("position_only", [False, True])
def test_whole_body_ik_solves_and_every_success_verifies(whole, position_only):
    x = whole.limits.sample(16, torch.Generator().manual_seed(11))
    pose = whole.pose_of_variables(x)
    target = pose[:, :3, 3] if position_only else pose
    result = solve_ik(whole, target, n_solutions=6, position_only=position_only, seeds=whole.seeds(target, 6))
    assert result.q.shape == (16, 6, 7 + TDCR3.num_joints) and result.q.dtype == F64
    assert result.success.all()
    assert_every_flagged_solution_verifies(whole, TDCR3, MOUNT, result, target)
    assert (result.distinct.sum(1) >= 3).all()


def test_warm_start_gives_the_nearby_solution_first(whole):
    """Least arm motion from a given configuration: with q0 the first solution is the one nearest q0."""
    x = whole.limits.sample(6, torch.Generator().manual_seed(12))
    q0 = whole.joints(x)
    moved = x.clone()
    moved[:, :7] += 0.02                                         # the target of a slightly moved arm
    target = whole.pose_of_variables(whole.limits.project(moved))
    result = solve_ik(whole, target, n_solutions=4, q0=q0, seeds=whole.seeds(target, 4))
    assert result.success[:, 0].all()
    first = (result.q[:, 0, :7] - q0[:, :7]).abs().amax(-1)
    others = (result.q[:, 1:, :7] - q0[:, None, :7]).abs().amax(-1)
    assert (first <= 0.1).all() and (first <= others.amin(-1)).all()


def test_unreachable_targets_fail_cleanly(whole):
    far = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    far[:, :3, 3] = torch.tensor([[3.0, 0.0, 0.5], [0.0, 0.0, -2.0]], dtype=F64)         # beyond the reach
    result = solve_ik(whole, far, n_solutions=2, options=IKOptions(restarts=1), seeds=whole.seeds(far, 2))
    assert not result.success.any() and torch.isfinite(result.q).all()
    assert whole.check(result.q.flatten(0, 1)).inside.all()                             # still admissible


def test_pose_bank_seeds_are_the_nearest_samples(whole):
    bank = PoseBank(whole, size=512, seed=3)
    target = whole.pose_of_variables(whole.limits.sample(4, torch.Generator().manual_seed(5)))
    seeds = bank.seeds(target, 3)
    assert seeds.shape == (4, 3, whole.limits.num_variables) and whole.limits.inside(seeds).all()
    p, r, _ = whole.tip_and_jacobian(bank.x)
    w = 10.0 / whole.length
    for i in range(4):                                            # brute force over the bank
        d = ((p - target[i, :3, 3]) * w).pow(2).sum(-1) + (r - target[i, :3, :3]).pow(2).sum((-2, -1))
        assert torch.equal(seeds[i], bank.x[d.argsort()[:3]])
    with pytest.raises(ValueError, match="count"):
        bank.seeds(target, 0)


class _TipOnly(SolverModel):
    """The CC robot seen as a position-only model (like a hardware model): no rotation, J (B, 3, D)."""

    has_rotation = False

    def __init__(self, spec):
        self.inner = ConstantCurvature(spec)
        for name in ("limits", "rest", "length", "num_joints", "spec"):
            setattr(self, name, getattr(self.inner, name))

    def tip_and_jacobian(self, x):
        p, _, j = self.inner.tip_and_jacobian(x)
        return p, None, j[:, :3]

    def joints(self, x):
        return self.inner.joints(x)

    def variables(self, q):
        return self.inner.variables(q)

    def check(self, q):
        c = self.inner.check(q)
        return Check(c.position, None, c.inside, c.constraint)


def test_a_position_only_robot_makes_a_position_only_whole_body(panda):
    model = Composite(panda, torch.from_numpy(MOUNT), _TipOnly(TDCR3))
    x = model.limits.sample(8, torch.Generator().manual_seed(6))
    position, rotation, jac = model.tip_and_jacobian(x)
    full = Composite(panda, torch.from_numpy(MOUNT), TDCR3).tip_and_jacobian(x)
    assert rotation is None and not model.has_rotation and torch.equal(jac, full[2][:, :3])
    with pytest.raises(ValueError, match="position_only"):
        solve_ik(model, torch.eye(4, dtype=F64)[None], n_solutions=1)
    result = solve_ik(model, position, n_solutions=3, position_only=True, seeds=model.seeds(position, 3))
    assert result.success.all()
    assert_every_flagged_solution_verifies(model, TDCR3, MOUNT, result, position)


# --------------------------------------------------------------------------------------------------
# Other continuum models on the arm: a trained FK network, a saved hardware model
# --------------------------------------------------------------------------------------------------

FIXTURES = ROOT / "tests" / "data" / "main_87f426b"     # tiny trained models (read only)


def test_a_learned_fk_on_the_arm_jacobian_and_ik(panda):
    """The robot is a trained compositional FK: J = jacrev of the whole (through the network) and IK solutions
    that reach the targets through the NumPy arm chain · mount · the network's own pose of the returned joints."""
    from dacr_learn.runs import load_model
    net = load_model(FIXTURES / "fk_compositional.ckpt", dtype=F64)
    model = Composite(panda, torch.from_numpy(MOUNT), net)
    x = model.limits.sample(1, torch.Generator().manual_seed(8))       # jacrev through the network: ~1 s
    _, _, jac = model.tip_and_jacobian(x)
    assert (jac - jacrev_twist(model, x)).abs().max() <= 1e-9           # the folded Jacobian vs autodiff
    target = model.pose_of_variables(model.limits.sample(6, torch.Generator().manual_seed(9))).detach()
    result = solve_ik(model, target, n_solutions=2, seeds=PoseBank(model, 1024).seeds(target, 2))   # a small bank
    assert result.success.any(1).all()
    ref = UrdfArm(PANDA, "panda_link8")
    for b, k in result.success.nonzero().tolist():
        q = result.q[b, k]
        with torch.no_grad():
            robot = net(q[None, 7:])[0].numpy()
        tip = ref.tip_pose(q[:7].numpy()) @ MOUNT @ robot
        assert np.linalg.norm(tip[:3, 3] - target[b, :3, 3].numpy()) <= POS_TOL
        assert ref.inside(q[:7].numpy())


def test_a_hardware_model_on_the_arm_is_position_only(panda):
    """Servo commands [mm] inside the recorded range behind the arm's joints; tips checked with the model's own
    predict(static) through the NumPy arm chain."""
    from dacr_learn.hardware.deploy import load_hardware_model
    hardware = load_hardware_model(FIXTURES / "hardware_model.pt")
    model = Composite(panda, torch.from_numpy(MOUNT), hardware)
    assert not model.has_rotation
    target = model.tip_and_jacobian(model.limits.sample(4, torch.Generator().manual_seed(10)))[0]
    result = solve_ik(model, target, n_solutions=2, position_only=True, seeds=PoseBank(model, 1024).seeds(target, 2))
    assert result.success.any(1).all()
    ref, commands = UrdfArm(PANDA, "panda_link8"), hardware.examples.to(F64)
    for b, k in result.success.nonzero().tolist():
        q = result.q[b, k]
        tip_c, _ = hardware.predict(q[None, 7:], static=True)
        tip = ref.tip_pose(q[:7].numpy()) @ MOUNT @ np.append(tip_c[0].double().numpy(), 1.0)
        assert np.linalg.norm(tip[:3] - target[b].numpy()) <= POS_TOL
        assert ref.inside(q[:7].numpy())
        assert (q[7:] >= commands.amin(0) - 1e-12).all() and (q[7:] <= commands.amax(0) + 1e-12).all()


def test_a_urdf_with_a_joint_type_pytorch_kinematics_lacks_is_named():
    floating = ('<robot name="f"><link name="a"/><link name="b"/><joint name="j" type="floating">'
                '<parent link="a"/><child link="b"/></joint></robot>')
    with pytest.raises(ValueError, match="floating"):
        load_arm(floating, "b")
