"""Follow-the-leader planning (dacr_learn.plan): the metric against hand-computed cases and a brute-force NumPy
reference, a straight path a straight robot follows with zero deviation, infeasible paths."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm, check_solution
from conftest import ROOT

from dacr_learn.arm import Composite, load_arm
from dacr_learn.ik import SolverModel, clarke_limits
from dacr_learn.plan import Path, plan_ftl, shape_deviation, tip_error
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
STAGE = ROOT / "configs" / "arms" / "insertion_stage.urdf"
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml"


def line(a, b, n=101):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return torch.from_numpy((1 - t) * np.asarray(a, float) + t * np.asarray(b, float))


def test_shape_deviation_of_a_parallel_body_is_its_offset():
    # path: the z axis from 0 to 1; body: the line x = 0.1 from z = -0.5 to 0.5 (arc 0 … 1), tip at z = 0.5,
    # so s = 0.5: the inserted half lies beside the traversed path P[0 … 0.5] at distance 0.1 everywhere
    path = Path(line([0, 0, 0], [0, 0, 1]))
    z = torch.linspace(-0.5, 0.5, 11, dtype=F64)
    body = torch.stack([torch.full_like(z, 0.1), torch.zeros_like(z), z], -1)[None]
    mean, worst = shape_deviation(body, z + 0.5, path, torch.tensor([0.5], dtype=F64))
    assert abs(float(mean[0]) - 0.1) < 1e-14 and abs(float(worst[0]) - 0.1) < 1e-14


def test_shape_deviation_past_the_traversed_end_by_hand():
    # the same body with its tip at z = 1 but s = 0.5: the inserted part (z = 0.5 … 1, x = 0.1) reaches past
    # the traversed path's end (0, 0, 0.5): distance sqrt(0.1² + u²) for u = z − 0.5, sampled evenly
    path = Path(line([0, 0, 0], [0, 0, 1]))
    z = torch.linspace(0.0, 1.0, 21, dtype=F64)
    body = torch.stack([torch.full_like(z, 0.1), torch.zeros_like(z), z], -1)[None]
    mean, worst = shape_deviation(body, z, path, torch.tensor([0.5], dtype=F64), samples=11)
    u = np.linspace(0.0, 0.5, 11)
    assert abs(float(mean[0]) - np.mean(np.sqrt(0.01 + u * u))) < 1e-14
    assert abs(float(worst[0]) - math.sqrt(0.01 + 0.25)) < 1e-14
    zero, _ = shape_deviation(body, z, path, torch.tensor([0.0], dtype=F64))       # nothing inserted
    assert float(zero[0]) == 0.0


def test_path_distance_matches_brute_force():
    gen = np.random.default_rng(0)
    t = np.linspace(0, 3, 400)
    points = np.stack([np.sin(t), np.cos(2 * t), t], -1)
    path = Path(torch.from_numpy(points))
    x = gen.normal(size=(6, 20, 3))
    upto = gen.uniform(0, path.length, 6)
    got = path.distance(torch.from_numpy(x), torch.from_numpy(upto)).numpy()
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    for i in range(6):                                          # the traversed polyline, then point-segment by hand
        k = np.searchsorted(arc, upto[i])
        end = points[k - 1] + (upto[i] - arc[k - 1]) / (arc[k] - arc[k - 1]) * (points[k] - points[k - 1])
        poly = np.concatenate([points[:k], end[None]])
        a, d = poly[:-1], np.diff(poly, axis=0)
        for j in range(20):
            tt = np.clip(((x[i, j] - a) * d).sum(-1) / (d * d).sum(-1), 0, 1)
            ref = np.linalg.norm(x[i, j] - a - tt[:, None] * d, axis=-1).min()
            assert abs(got[i, j] - ref) < 1e-12
    assert float(tip_error(path.points[:1], path, torch.zeros(1, dtype=F64))[0]) == 0.0


def test_path_rejects_bad_input():
    with pytest.raises(ValueError, match="coincide"):
        Path(torch.tensor([[0.0, 0, 0], [0, 0, 0], [0, 0, 1]]))
    with pytest.raises(ValueError, match=r"\(W, 3\)"):
        Path(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="NaN"):
        Path(torch.tensor([[0.0, 0, 0], [float("nan"), 0, 1]]))


def stage_model() -> Composite:
    return Composite(load_arm(STAGE, "carriage"), torch.eye(4, dtype=F64), RobotSpec.from_yaml(ROBOT))


def test_a_straight_robot_follows_a_straight_path_with_zero_deviation():
    model = stage_model()
    length = model.robot.length                                             # 0.27 m
    path = line([0, 0, 0.3], [0, 0, 0.55])
    plan = plan_ftl(model, path, steps=12)
    assert plan.success, plan.reason
    assert plan.q.shape == (12, 1 + model.robot.num_joints)
    assert torch.allclose(plan.s, torch.linspace(0, 0.25, 12, dtype=F64), atol=1e-15)
    assert float(plan.shape_dev_max.max()) <= 1e-9 * length
    ref = UrdfArm(STAGE, "carriage")
    for q, s in zip(plan.q.numpy(), plan.s.numpy(), strict=True):          # independent NumPy check of each step
        pos, _, inside = check_solution(ref, np.eye(4), model.robot.spec, q, np.array([0, 0, 0.3 + s]))
        assert inside and pos <= 1e-6 * length


def test_a_start_out_of_reach_fails_with_a_reason():
    plan = plan_ftl(stage_model(), line([1.0, 0, 0.3], [1.0, 0, 0.5]), steps=5)
    assert not plan.success and "cannot reach the path's start" in plan.reason
    assert plan.q.shape[0] == 5 and plan.tip_err.shape == (5,)


def test_a_path_leaving_the_workspace_fails_with_a_reason():
    # the stage moves along z only: a path turning sideways 0.5 m leaves what the 0.27 m robot can reach
    model = stage_model()
    plan = plan_ftl(model, line([0, 0, 0.3], [0.5, 0, 0.3]), steps=6)
    assert not plan.success and "tip" in plan.reason
    assert float(plan.tip_err.max()) > 1e-6 * model.robot.length


def test_a_model_without_a_body_is_refused():
    class NoBody(SolverModel):
        limits = clarke_limits(RobotSpec.from_yaml(ROBOT))
    with pytest.raises(ValueError, match="NoBody: has no body"):
        plan_ftl(NoBody(), line([0, 0, 0], [0, 0, 1]))


def test_a_plan_through_a_wide_open_scene_keeps_its_clearance():
    # one sphere 0.3 m beside the straight path: the clearance of each step by hand (the straight body on the
    # z axis from z = 0.3 + s − L … 0.3 + s, swept by the last segment's envelope radius)
    model = stage_model()
    center, radius, envelope = np.array([0.3, 0.0, 0.45]), 0.05, model.robot.spec.segments[-1].body_radius
    scene = {"obstacles": [{"type": "sphere", "center": center.tolist(), "radius": radius}]}
    plan = plan_ftl(model, line([0, 0, 0.3], [0, 0, 0.55]), steps=12,
                    scene=scene, clearance=0.01)
    assert plan.success, plan.reason
    assert plan.clearance.shape == (12,) and plan.arrays()["clearance"].shape == (12,)
    z = np.clip(center[2], 0.3 + plan.s.numpy() - model.robot.length, 0.3 + plan.s.numpy())
    exact = np.hypot(center[0], center[2] - z) - radius - envelope
    assert np.all(plan.clearance.numpy() >= 0.01)
    bent = float(plan.shape_dev_max.max())                          # the body off the axis (≤ 1e-9 L here)
    assert np.all(plan.clearance.numpy() <= exact + bent + 1e-12)
    assert np.allclose(plan.clearance.numpy(), exact, atol=1e-4)


def test_an_obstacle_on_the_path_fails_naming_the_clearance():
    # a sphere of radius 10 mm on the path at z = 0.5: the tip (z = 0.3 + s) comes within D = 10 mm of its surface
    # (8 steps: the first step inside D is still clear of the surface, by 3.4 mm; 12 steps took 5x the CPU)
    model = stage_model()
    envelope = model.robot.spec.segments[-1].body_radius
    scene = {"obstacles": [{"type": "sphere", "center": [0.0, 0.0, 0.5], "radius": 0.01}]}
    plan = plan_ftl(model, line([0, 0, 0.3], [0, 0, 0.55]), steps=8,
                    scene=scene, clearance=0.01)
    assert not plan.success and "clearance" in plan.reason
    s = plan.s.numpy()
    first = int(np.argmax(0.49 - (0.3 + s) - envelope < 0.01))                     # by hand: the tip's ball
    assert f"at step {first} " in plan.reason
    below = 0.3 + s < 0.49
    assert np.allclose(plan.clearance.numpy()[below], (0.49 - (0.3 + s) - envelope)[below], atol=1e-9)
    assert float(plan.tip_err.max()) <= 1e-6 * model.robot.length             # the tip still follows the path


def s_curve(end, n: int = 1001) -> torch.Tensor:
    """The S curve of the sampling-based FTL benchmark: a cubic Bézier from the origin to ``end`` whose control
    points sit half-way in x (a quarter and three quarters), 0.5 above and below the middle height."""
    end = np.asarray(end, float)
    c1 = np.array([end[0] / 4, 0.0, end[2] / 2 + 0.5])
    c2 = np.array([end[0] - end[0] / 4, end[1], end[2] / 2 - 0.5])
    t = np.linspace(0.0, 1.0, n)[:, None]
    return torch.from_numpy(3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t ** 2 * c2 + t ** 3 * end)


@pytest.mark.slow
def test_an_s_curve_whose_base_turns_fast_is_followed_continuously():
    # a curve of the benchmark (seed 0) on which the free base's roll turns 0.05 rad per step of 1 % L: an earlier
    # batch pass left one step behind its neighbours (a jump of 0.14 rad); the continuation follows it
    model = Composite(load_arm(ROOT / "configs" / "arms" / "free_base.urdf", "tool"), torch.eye(4, dtype=F64),
                      ROOT / "configs" / "robots" / "ftl_3seg_unit.yaml")
    path = s_curve([-2.5254300341002613, 0.1023746488161782, 0.8883137069445501])
    plan = plan_ftl(model, path)
    assert plan.success, plan.reason
    length = model.robot.length
    q, s = plan.q.numpy(), plan.s.numpy()
    bound = 0.1 * np.diff(s)[:, None] / (0.01 * length)                   # rad per step (docs/plan.md)
    assert np.all(np.abs(np.diff(q[:, 3:6], axis=0)) <= bound)             # yaw, pitch, roll: continuous
    assert np.all(np.abs(np.diff(q[:, :3], axis=0)) <= bound * length)    # x, y, z [m]
    ref = UrdfArm(ROOT / "configs" / "arms" / "free_base.urdf", "tool")
    points = path.numpy()
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    for qk, sk in zip(q[::5], s[::5], strict=True):                        # the tip in NumPy, every 5th step
        target = np.array([np.interp(sk, arc, points[:, i]) for i in range(3)])
        pos, _, inside = check_solution(ref, np.eye(4), model.robot.spec, qk, target)
        assert inside and pos <= 1e-6 * length
    assert 100 * float(plan.shape_dev.mean()) / length < 0.5               # % of L (the peer: 1.4 % on its curves)
