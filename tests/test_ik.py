"""The IK solver (dacr_learn.ik) against independent references: every flagged solution is re-checked with NumPy
geometry that shares no code with the solver (the joint vector of docs/design.md §1 and the classic arc FK)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import (
    FAST,
    TDCR3,
    classic_forward_kinematics,
    random_features,
    reference_joint_vector,
    robots,
    spec_by_name,
)
from hypothesis import given
from hypothesis import strategies as st

from dacr_learn.ik import ConstantCurvature, IKOptions, Limits, clarke_limits, levenberg_marquardt, solve_ik
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec

F64 = torch.float64
POS_TOL, ROT_TOL = 1e-6, 1e-5


def targets_of(spec: RobotSpec, n: int, seed: int, **kw) -> torch.Tensor:
    return forward_kinematics(spec, random_features(spec, (n,), seed, **kw))


def independent_check(spec: RobotSpec, q: np.ndarray, target: np.ndarray) -> tuple[float, float, bool]:
    """(position error [m], rotation error [rad], inside the limits) of one joint vector, from NumPy geometry.

    The features are proposed by the library's encoder but accepted only if the independent joint-vector
    geometry reproduces q from them (to 1e-9 m): then q lies on the displacement constraint and has those
    features; the tip comes from the classic arc formula, the limits from the robot file's numbers."""
    f = ClarkeEncoder(spec).to(F64)(torch.from_numpy(q)).numpy()
    assert np.abs(reference_joint_vector(spec, f) - q).max() < 1e-9, "q is not on the displacement constraint"
    tip = classic_forward_kinematics(spec, f)
    inside = True
    for k, seg in enumerate(spec.segments):
        inside &= math.hypot(f[k, 0], f[k, 1]) / seg.radius <= seg.bend * (1 + 1e-9)
        if seg.extends:
            inside &= seg.length_range[0] - 1e-12 <= f[k, 2] <= seg.length_range[1] + 1e-12
        if seg.twists:
            inside &= seg.twist_range[0] - 1e-12 <= f[k, 3] <= seg.twist_range[1] + 1e-12
    if target.shape == (3,):
        return float(np.linalg.norm(tip[:3, 3] - target)), 0.0, bool(inside)
    r = tip[:3, :3] @ target[:3, :3].T
    angle = math.atan2(np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2,
                       (np.trace(r) - 1) / 2)
    return float(np.linalg.norm(tip[:3, 3] - target[:3, 3])), angle, bool(inside)


def assert_flagged_solutions_verify(spec: RobotSpec, result, target: torch.Tensor) -> None:
    for b, k in result.success.nonzero().tolist():
        pos, rot, inside = independent_check(spec, result.q[b, k].numpy(), target[b].numpy())
        assert inside and pos <= POS_TOL * 1.01 and rot <= ROT_TOL * 1.01, (b, k, pos, rot, inside)


# --------------------------------------------------------------------------------------------------
# Pose and position IK on the analytic model: exact, inside the limits, several solutions
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "hetero_4seg_types", "twisting"])
@pytest.mark.parametrize("position_only", [False, True])
def test_solutions_verify_independently_and_are_distinct(robot, position_only):
    spec = spec_by_name(robot)
    poses = targets_of(spec, 12, seed=1)
    target = poses[:, :3, 3] if position_only else poses
    result = solve_ik(spec, target, n_solutions=6, position_only=position_only)
    assert result.q.shape == (12, 6, spec.num_joints) and result.q.dtype == F64
    assert result.success.all(), result.success.sum(1)
    assert_flagged_solutions_verify(spec, result, target)
    assert (result.distinct.sum(1) >= 3).all()                    # ≥ K/2 distinct (these robots are redundant)
    q = result.q
    for b in range(12):                                           # "distinct" means some joint differs ≥ 0.5 mm
        kept = q[b, result.distinct[b]]
        gap = (kept.unsqueeze(0) - kept.unsqueeze(1)).abs().amax(-1) + torch.eye(len(kept), dtype=F64)
        assert (gap >= 5e-4).all()
    assert torch.isfinite(result.pos_err).all() and torch.isfinite(result.rot_err).all()


@FAST
@given(spec=robots(max_segments=3), seed=st.integers(0, 2**16))
def test_property_random_robots_of_every_type(spec, seed):
    poses = targets_of(spec, 3, seed)
    position_only = seed % 2 == 1
    target = poses[:, :3, 3] if position_only else poses
    result = solve_ik(spec, target, n_solutions=3, position_only=position_only, options=IKOptions(seed=seed))
    assert_flagged_solutions_verify(spec, result, target)
    assert result.success.any(1).all(), (result.pos_err, result.rot_err)


@pytest.mark.parametrize("position_only", [False, True])
def test_working_batch_and_grouped_restarts_agree_in_kind(position_only):
    """Both paths of the solver (the working batch that stays full, with a batch smaller than the slots so starts
    queue, and the grouped restarts) solve every slot, verified independently, with ≥ K/2 distinct solutions."""
    spec = spec_by_name("hetero_3seg_coupled")
    poses = targets_of(spec, 6, seed=4)
    target = poses[:, :3, 3] if position_only else poses
    for options in (IKOptions(pool=0), IKOptions(pool=16)):
        result = solve_ik(spec, target, n_solutions=6, position_only=position_only, options=options)
        assert result.success.all(), (options, result.success.sum(1))
        assert_flagged_solutions_verify(spec, result, target)
        assert (result.distinct.sum(1) >= 3).all() and (result.iterations >= 1).all()


def test_sharded_solve_is_reproducible_and_independent_of_the_threads():
    """Targets split into a given number of shards give the same solutions on 1 and 2 threads and for the same seed
    twice; every flagged solution verifies."""
    from dacr_learn.ik import pool
    assert [(s.start, s.stop) for s in pool.shards(9, 3)] == [(0, 3), (3, 6), (6, 9)]
    target = targets_of(TDCR3, 9, seed=5)
    before = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            runs.append(solve_ik(TDCR3, target, n_solutions=4, options=IKOptions(seed=3, shards=3)))
            assert torch.get_num_threads() == threads                  # restored after the threaded shards
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        assert torch.equal(runs[0].q, other.q) and torch.equal(runs[0].success, other.success)
    assert runs[0].success.all()
    assert_flagged_solutions_verify(TDCR3, runs[0], target)


def test_straight_and_boundary_targets():
    """The straight robot (the singular configuration of the Clarke parameterisation's θ) and targets at the
    bending and length limits are solved inside the limits."""
    spec = TDCR3
    straight = random_features(spec, (2,), 0, straight=True)
    rim = random_features(spec, (2,), 1, bend_scale=1.0)
    rho = rim[..., :2]
    rim[..., :2] = rho / rho.norm(dim=-1, keepdim=True) * torch.tensor([s.bend * s.radius for s in spec.segments],
                                                                       dtype=F64).unsqueeze(-1)
    rim[..., 2] = torch.tensor([s.length_range[1] for s in spec.segments], dtype=F64)
    target = forward_kinematics(spec, torch.cat([straight, rim]))
    result = solve_ik(spec, target, n_solutions=4)
    assert result.success.all()
    assert_flagged_solutions_verify(spec, result, target)


def test_warm_start_comes_first_and_stays_there():
    spec = TDCR3
    feats = random_features(spec, (5,), 3)
    target = forward_kinematics(spec, feats)
    q_true = ClarkeDecoder(spec).to(F64)(feats)
    result = solve_ik(spec, target, n_solutions=4, q0=q_true + 1e-4)
    assert result.success[:, 0].all()
    assert ((result.q[:, 0] - q_true).abs().amax(-1) < 1e-3).all()         # the solution near q0, first
    near = (result.q - (q_true + 1e-4).unsqueeze(1)).abs().amax(-1)
    assert (near[:, 0:1] <= near + 1e-12).all()


def test_unreachable_target_is_flagged_with_the_closest_admissible_configuration():
    spec = TDCR3
    far = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
    far[0, :3, 3] = torch.tensor([0.0, 0.0, 1.0])                 # beyond the longest robot
    far[1, :3, 3] = torch.tensor([0.0, 0.0, -0.1])                # behind the base
    result = solve_ik(spec, far[:, :3, 3], n_solutions=2, position_only=True)
    assert not result.success.any() and torch.isfinite(result.q).all()
    assert clarke_limits(spec).inside(ConstantCurvature(spec).variables(result.q[:, 0])).all()
    f = ClarkeEncoder(spec).to(F64)(result.q[0, 0])
    # the closest admissible configuration is the straight robot at its longest: its tip error is that
    # distance to within the tolerance (the error is flat, second order, in the bending near straight)
    longest = torch.tensor([s.length_range[1] for s in spec.segments], dtype=F64)
    assert torch.allclose(f[:, :2], torch.zeros(3, 2, dtype=F64), atol=1e-4) and torch.allclose(f[:, 2], longest)
    assert result.pos_err[0, 0] == pytest.approx(1.0 - float(longest.sum()), abs=POS_TOL)


@pytest.mark.parametrize("bad, message", [
    (torch.zeros(3, 4), "expected (B, 4, 4) poses"),
    (torch.full((2, 4, 4), float("nan")), "NaN/inf"),
    (torch.eye(4).expand(2, 4, 4) * 2, "not a rotation matrix"),
    (torch.zeros(2, 4, 4, dtype=torch.long), "floating-point"),
])
def test_bad_targets_raise_a_value_error_naming_the_problem(bad, message):
    with pytest.raises(ValueError, match="target: .*" + message.replace("(", r"\(").replace(")", r"\)")):
        solve_ik(TDCR3, bad, n_solutions=2)


def test_bad_arguments_raise():
    target = targets_of(TDCR3, 2, 0)
    with pytest.raises(ValueError, match="n_solutions"):
        solve_ik(TDCR3, target, n_solutions=0)
    with pytest.raises(ValueError, match="q0: expected a warm start of shape"):
        solve_ik(TDCR3, target, q0=torch.zeros(5, dtype=F64))
    with pytest.raises(ValueError, match="model_or_spec"):
        solve_ik(42, target)


# --------------------------------------------------------------------------------------------------
# The pieces: limits, the LM refinement
# --------------------------------------------------------------------------------------------------


def test_limits_projection_is_the_nearest_admissible_point():
    lim = Limits.concatenate(Limits.disk(0.5, ("a", "b")), Limits.boxes([0.0], [1.0], ("c",)))
    assert torch.equal(lim.lower, torch.tensor([-math.inf, -math.inf, 0.0], dtype=F64))
    assert torch.equal(lim.disks, torch.tensor([[0, 1]])) and torch.equal(lim.scale, torch.full((3,), 0.5, dtype=F64))
    g = torch.Generator().manual_seed(0)
    x = torch.randn(200, 3, generator=g, dtype=F64)
    p = lim.project(x)
    assert lim.inside(p).all() and lim.inside(lim.sample(500, g)).all()
    candidates = lim.sample(20000, g)                                   # no admissible point is nearer
    nearest = torch.cdist(x, candidates).amin(-1)
    assert ((x - p).norm(dim=-1) <= nearest + 1e-12).all()
    assert torch.allclose(lim.project(p), p, rtol=0, atol=1e-15)            # idempotent up to rounding


def test_levenberg_marquardt_converges_quadratically_near_a_solution():
    spec = TDCR3
    model = ConstantCurvature(spec)
    feats = random_features(spec, (8,), 5, bend_scale=0.8)
    target = forward_kinematics(spec, feats)
    x_true = model.variables(ClarkeDecoder(spec).to(F64)(feats))
    x, pos_err, rot_err, iters = levenberg_marquardt(model, x_true + 1e-3 * model.limits.scale, target[:, :3, 3],
                                                     target[:, :3, :3])
    assert model.limits.inside(x).all()
    assert (pos_err < 1e-7).all() and (rot_err < 1e-6).all() and (iters <= 6).all()


@pytest.mark.parametrize("n", [3, 6])
def test_unrolled_spd_solve_equals_torch(n):
    from dacr_learn.ik.refine import spd_solve_unrolled
    g = torch.Generator().manual_seed(n)
    m = torch.randn(40, n, n, generator=g, dtype=F64)
    a = m @ m.mT + 1e-3 * torch.eye(n, dtype=F64)
    b = torch.randn(40, n, generator=g, dtype=F64)
    x = spd_solve_unrolled(a, b)
    expected = torch.linalg.solve(a, b)
    cond = torch.linalg.cond(a)                                  # the error bound scales with the conditioning
    assert ((x - expected).abs().amax(-1) <= 64 * torch.finfo(F64).eps * cond * expected.abs().amax(-1)).all()


def test_limits_concatenation_shifts_the_disks_and_keeps_every_bound():
    """Limits.concatenate of (box, disk, box, disk) equals the limits written out by hand, variable by variable."""
    parts = [Limits.boxes([-1.0, 2.0], [1.0, 5.0], ("p", "q"), scale=[0.1, 0.2]), Limits.disk(0.3, ("r", "s")),
             Limits.boxes([0.0], [4.0], ("t",)), Limits.disk(2.0, ("u", "v"))]
    lim = Limits.concatenate(*parts)
    inf = math.inf
    assert lim.lower.tolist() == [-1.0, 2.0, -inf, -inf, 0.0, -inf, -inf]
    assert lim.upper.tolist() == [1.0, 5.0, inf, inf, 4.0, inf, inf]
    assert lim.disks.tolist() == [[2, 3], [5, 6]] and lim.radius.tolist() == [0.3, 2.0]
    assert lim.scale.tolist() == [0.1, 0.2, 0.3, 0.3, 2.0, 2.0, 2.0] and lim.names == tuple("pqrstuv")
    assert Limits.concatenate(*parts, names=tuple("abcdefg")).names == tuple("abcdefg")
    x = torch.tensor([[0.0, 3.0, 0.3, 0.0, 2.0, 1.5, 1.5]], dtype=F64)       # second disk: ‖(1.5, 1.5)‖ > 2
    assert lim.violation(x).item() == pytest.approx((math.hypot(1.5, 1.5) - 2.0) / 2.0, rel=1e-12)
    with pytest.raises(ValueError, match="lower < upper"):
        Limits.boxes([1.0], [1.0], ("w",))


@pytest.mark.parametrize(("field", "value", "unit"),
                         [("pos_tolerance", 0.0, "m"), ("rot_tolerance", math.nan, "rad"),
                          ("pos_tolerance", math.inf, "m")])
def test_ik_options_name_a_bad_tolerance(field, value, unit):
    with pytest.raises(ValueError) as err:
        IKOptions(**{field: value})
    assert str(err.value) == f"{field}: expected a finite value > 0 [{unit}], got {value}"


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "hetero_4seg_types"])
def test_held_limits_without_the_projector_equal_the_projector(robot):
    """free_jacobian's whole-tensor path (only_held) is J̃·P, P the projector of Limits.free_directions."""
    from dacr_learn.ik.refine import free_jacobian
    lim = ConstantCurvature(spec_by_name(robot)).limits
    g = torch.Generator().manual_seed(5)
    x = lim.project(lim.sample(400, g) * 1.6)                       # many on a rim or a bound
    ja = torch.randn(400, 6, lim.num_variables, dtype=torch.float64, generator=g)
    gradient = torch.randn(400, lim.num_variables, dtype=torch.float64, generator=g)
    held, none = free_jacobian(lim, x, ja, gradient, only_held=True)
    full, proj = free_jacobian(lim, x, ja, gradient)
    box, normals = lim.blocked(x, gradient)
    assert none is None and box.any() and (normals != 0).any()
    assert (held - ja @ proj).abs().max() <= 1e-14 and (full - held).abs().max() <= 1e-14
