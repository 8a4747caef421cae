"""Follow-the-leader through a channel of capsules (dacr_learn.plan with a scene): the planned body checked
against the obstacles independently, densely in NumPy (the arc formula of tests/conftest.py, the URDF by hand,
exact point-to-segment distances)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm
from conftest import ROOT, reference_backbone

from dacr_learn.arm import Composite, load_arm
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.plan import plan_ftl
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
ARM = ROOT / "configs" / "arms" / "free_base.urdf"
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml"


def channel(points: np.ndarray, ring: float, radius: float, pieces: int = 4, around: int = 6) -> list[dict]:
    """Capsules of ``radius`` parallel to ``pieces`` chords of the path, ``around`` per chord on a ring of
    radius ``ring`` about it (the path bends in the x–z plane: ring axes y and the chord's normal in x–z)."""
    ends = np.linspace(0, len(points) - 1, pieces + 1).round().astype(int)
    out = []
    for i, j in zip(ends[:-1], ends[1:], strict=True):
        a, b = points[i], points[j]
        t = (b - a) / np.linalg.norm(b - a)
        n = np.cross([0.0, 1.0, 0.0], t)
        for k in range(around):
            off = ring * (np.cos(2 * np.pi * k / around) * n + np.sin(2 * np.pi * k / around) * np.array([0, 1.0, 0]))
            out.append({"type": "capsule", "a": (a + off).tolist(), "b": (b + off).tolist(), "radius": radius})
    return out


def dense_clearance(q: np.ndarray, spec: RobotSpec, capsules: list[dict], per_segment: int = 200) -> np.ndarray:
    """The robot body's clearance (T,) [m] to the capsules: backbone points by the arc formula in the base pose
    of the URDF computed by hand, exact distances to each capsule's axis, less both radii."""
    arm = UrdfArm(ARM, "tool")
    a = np.array([c["a"] for c in capsules])
    d = np.array([c["b"] for c in capsules]) - a
    radius = np.array([c["radius"] for c in capsules])
    envelope = max(s.body_radius for s in spec.segments)
    encoder = ClarkeEncoder(spec).to(F64)
    out = []
    for qk in q:
        features = encoder(torch.from_numpy(np.ascontiguousarray(qk[6:]))).numpy()
        local = reference_backbone(spec, features, per_segment)
        base = arm.tip_pose(qk[:6])
        pts = local @ base[:3, :3].T + base[:3, 3]
        t = np.clip(np.einsum("poi,oi->po", pts[:, None] - a, d) / (d * d).sum(-1), 0.0, 1.0)
        gap = np.linalg.norm(pts[:, None] - a - t[..., None] * d, axis=-1) - radius
        out.append(gap.min() - envelope)
    return np.array(out)


@pytest.mark.slow
def test_a_plan_through_a_channel_keeps_its_clearance_by_a_dense_check():
    # an arc of radius 0.3 m, 0.12 m long, inside a channel of capsules whose surfaces lie 2 mm beyond the
    # robot's envelope from the path; D = 1 mm
    angle = np.linspace(0.0, 0.12 / 0.3, 61)
    points = np.stack([0.3 * (1 - np.cos(angle)), np.zeros_like(angle), 0.3 * np.sin(angle)], -1)
    spec = RobotSpec.from_yaml(ROBOT)
    envelope, radius = max(s.body_radius for s in spec.segments), 0.003
    capsules = channel(points, envelope + 0.002 + radius, radius)
    model = Composite(load_arm(ARM, "tool"), torch.eye(4, dtype=F64), spec)
    plan = plan_ftl(model, torch.from_numpy(points), steps=9, scene={"obstacles": capsules}, clearance=0.001)
    assert plan.success, plan.reason
    dense = dense_clearance(plan.q.numpy(), spec, capsules)
    assert np.all(dense >= 0.001 - 1e-9), dense                       # the plan keeps D, by the dense check
    assert np.all(plan.clearance.numpy() <= dense + 1e-9)            # the planner's check is a lower bound
    assert float(plan.tip_err.max()) <= 1e-6 * spec.total_length


def test_the_clearance_hinges_bend_the_body_around_an_obstacle_beside_the_path():
    # the insertion stage (z) carries the robot up the z axis from z = 0.3; a sphere beside the entry line (z = 0.2,
    # as at a port), its surface 0.7 mm from the straight body's envelope: the straight body (the plan without the
    # scene) keeps only 0.7 mm; with the scene
    # and D = 1 mm the hinges bend the body away (tip still on the path) and every step keeps D (by hand: the
    # sphere's distance to the body's points, densely, less both radii)
    stage = ROOT / "configs" / "arms" / "insertion_stage.urdf"
    spec = RobotSpec.from_yaml(ROBOT)
    model = Composite(load_arm(stage, "carriage"), torch.eye(4, dtype=F64), spec)
    envelope, radius = max(s.body_radius for s in spec.segments), 0.004
    center = np.array([envelope + 0.0007 + radius, 0.0, 0.2])
    scene = {"obstacles": [{"type": "sphere", "center": center.tolist(), "radius": radius}]}
    path = torch.from_numpy(np.stack([np.zeros(21), np.zeros(21), np.linspace(0.3, 0.4, 21)], -1))
    free = plan_ftl(model, path, steps=5)
    assert free.success and float(free.shape_dev_max.max()) < 1e-9                  # straight, on the path
    plan = plan_ftl(model, path, steps=5, scene=scene, clearance=0.001)
    assert plan.success, plan.reason
    assert float(plan.tip_err.max()) <= 1e-6 * spec.total_length
    def gap_of(q):                                 # (T,) [m] by hand from the body API's points, 64 per segment
        pts = model.body(model.variables(q), 64).points.numpy()
        return np.linalg.norm(pts - center, axis=-1).min(-1) - radius - envelope

    assert np.all(gap_of(free.q) < 0.00075)                                        # without hinges: ≈ 0.7 mm
    gap = gap_of(plan.q)
    assert np.all(gap >= 0.001 - 1e-9), gap
    assert np.all(plan.clearance.numpy() >= 0.001) and np.all(plan.clearance.numpy() <= gap + 1e-9)
    assert float(plan.shape_dev_max.max()) > 0.0002                                 # the body left the path
