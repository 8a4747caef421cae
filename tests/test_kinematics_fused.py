"""The batched closed-form tip pose and Jacobian (kinematics.cc_pose_and_jacobian) against independent references:
the per-component chain rule of dacr_learn.lie (the kernel it replaced, written out here), central differences of
forward_kinematics, and reverse-mode autodiff (tests/test_kinematics.py), on random robots of every segment type."""
from __future__ import annotations

import pytest
import torch
from conftest import FAST, random_features, robots, roundoff_tol, spec_by_name
from hypothesis import given
from hypothesis import strategies as st
from test_kinematics import straight_and_near_straight

from dacr_learn.component_algebra import dense
from dacr_learn.kinematics import cc_pose_and_jacobian, forward_kinematics
from dacr_learn.lie import chain_components, exp_components_and_tangents, pose_of_components, roll_components, vee
from dacr_learn.models import actuated_columns
from dacr_learn.robot import RobotSpec

F64 = torch.float64
_COLUMN = {"rho_re": 0, "rho_im": 1, "beta": 2, "alpha": 3}


def component_pose_and_jacobian(spec: RobotSpec, features: torch.Tensor, columns=None):
    """Reference: the per-segment, per-component kernel (lie's exponential with tangents, roll and chain rule, one
    small tensor per vector component and segment): features (..., m, 4) → pose (..., 4, 4), J (..., 6, m, 4) or
    (..., 6, len(columns))."""
    m = spec.num_segments
    radius = torch.tensor([s.radius for s in spec.segments], dtype=F64)
    extends = torch.tensor([float(s.extends) for s in spec.segments], dtype=F64)
    twists = torch.tensor([float(s.twists) for s in spec.segments], dtype=F64)
    length = torch.tensor([s.length for s in spec.segments], dtype=F64)
    front = lambda t: t.movedim(-1, 0).contiguous()  # noqa: E731
    per_seg = lambda c: c.view(m, *([1] * (features.dim() - 2)))  # noqa: E731
    ux, uy = front(features[..., 0] / radius), front(features[..., 1] / radius)
    beta = front(torch.where(extends.bool(), features[..., 2], length))
    basis = [((None, None, None), (None, per_seg(1 / radius), None)),
             ((None, None, None), (-per_seg(1 / radius), None, None)),
             ((None, None, per_seg(extends)), (None, None, None)), ((None, None, None), (None, None, None))]
    rot, pos, tangents = exp_components_and_tangents((None, None, beta), (-uy, ux, None), basis)
    rot, pos, tangents = roll_components(front(features[..., 3] * twists), rot, pos, tangents, (3, per_seg(twists)))
    seg = lambda c, k: tuple(None if x is None else x[k] for x in c)  # noqa: E731
    like = beta[0]
    stacked = lambda vs, k: tuple(torch.stack(dense([seg(v, k)[i] for v in vs], like)) for i in range(3))  # noqa: E731
    tip_rot, tip_pos, cols = chain_components(
        [seg(rot, k) for k in range(m)], [seg(pos, k) for k in range(m)],
        [[(stacked([a for a, _ in tangents], k), stacked([v for _, v in tangents], k))] for k in range(m)])
    full = torch.stack([torch.stack([torch.stack([*cols[k][0][0], *cols[k][0][1]])[i] for k in range(m)], -1)
                        for i in range(6)]).movedim(1, -1)                                  # (6, ..., m, 4)
    full = full.movedim(0, -3)                                                             # (..., 6, m, 4)
    if columns is not None:
        full = torch.stack([full[..., k, c] for k, c in columns], -1)
    return pose_of_components(tip_rot, tip_pos), full


def scale_of(spec: RobotSpec) -> float:
    """The size of a Jacobian entry: a length over a radius (ρ columns)."""
    return 10.0 * spec.total_length / min(s.radius for s in spec.segments)


@given(spec=robots(max_segments=4), seed=st.integers(0, 2**16), straight=st.booleans())
@FAST
def test_fused_kernel_equals_the_component_kernel_on_random_robots(spec, seed, straight):
    feats = straight_and_near_straight(spec, 2) if straight else random_features(spec, (3, 5), seed)
    columns = [(k, _COLUMN[n]) for k, n in actuated_columns(spec)]
    for cols in (None, columns, [(spec.num_segments - 1, 3), (0, 2), (0, 0)]):
        pose, jac = cc_pose_and_jacobian(spec, feats, cols)
        ref_pose, ref_jac = component_pose_and_jacobian(spec, feats, cols)
        assert pose.shape == ref_pose.shape and jac.shape == ref_jac.shape
        assert (pose - ref_pose).abs().max() <= 1e-12 * spec.total_length
        assert (jac - ref_jac).abs().max() <= 1e-12 * scale_of(spec)


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "hetero_4seg_types", "hetero_5seg_coupled", "type3"])
def test_fused_kernel_is_the_central_difference_of_forward_kinematics(robot):
    spec = spec_by_name(robot)
    feats = random_features(spec, (4,), 5)
    pose, jac = cc_pose_and_jacobian(spec, feats)                                         # (4, 6, m, 4)
    h = 1e-6
    for k in range(spec.num_segments):
        for c, scale in enumerate((spec.segments[k].radius, spec.segments[k].radius, 1.0, 1.0)):
            step = torch.zeros_like(feats)
            step[:, k, c] = h * scale
            plus, minus = forward_kinematics(spec, feats + step), forward_kinematics(spec, feats - step)
            dpose = (plus - minus) / (2 * h * scale)
            omega = vee(dpose[:, :3, :3] @ pose[:, :3, :3].mT)
            expected = torch.cat([dpose[:, :3, 3], omega], -1)
            tol = 1e-8 * scale_of(spec)                                                  # O(h²) and roundoff/h
            assert (jac[:, :, k, c] - expected).abs().max() <= tol, (k, c)


def test_fused_kernel_batch_shapes_and_layout():
    spec = spec_by_name("hetero_4seg_types")
    feats = random_features(spec, (2, 3), 9)
    pose, jac = cc_pose_and_jacobian(spec, feats)
    assert pose.shape == (2, 3, 4, 4) and jac.shape == (2, 3, 6, 4, 4)
    one_pose, one_jac = cc_pose_and_jacobian(spec, feats[1, 2])                           # no batch dims
    assert one_pose.shape == (4, 4) and one_jac.shape == (6, 4, 4)
    assert (one_jac - jac[1, 2]).abs().max() <= roundoff_tol(F64, scale_of(spec))
    assert torch.equal(pose[..., 3, :], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(2, 3, 4))
    with pytest.raises(ValueError, match="features"):
        cc_pose_and_jacobian(spec, feats[..., :3])
