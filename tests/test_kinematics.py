"""Constant-curvature kinematics against independent references.

References: the classic arc Rz(θ)Ry(φ)Rz(−θ) (numpy, conftest.classic_forward_kinematics) and an
equivalent rigid-link chain evaluated by pytorch_kinematics from a URDF string (per segment:
[rz α], rz θ, ry φ/2, prismatic z by the chord 2β·sin(φ/2)/φ, ry φ/2, rz −θ).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import pytorch_kinematics as pk
import torch
from conftest import (
    FAST,
    ROBOT_CONFIGS,
    arc_parameters,
    chain_joint_values,
    classic_arc,
    classic_forward_kinematics,
    random_features,
    reference_backbone,
    robots,
    rot_z,
    roundoff_tol,
    seeds,
    urdf_chain_string,
    urdf_end_link,
)
from hypothesis import given
from hypothesis import strategies as st

from dacr_learn.kinematics import (
    analytic_inverse_kinematics,
    backbone_points,
    forward_kinematics,
    segment_poses,
    segment_tip_poses,
)
from dacr_learn.lie import bending_coefficients
from dacr_learn.robot import RobotSpec

F64 = torch.float64


def one_segment(seg_type: str = "I", **kw) -> RobotSpec:
    seg = {"type": seg_type, "length": 0.1, "radius": 0.008, "joints": 4, **kw}
    return RobotSpec.from_dict({"segments": [seg]})


def straight_and_near_straight(spec: RobotSpec, batch: int = 8) -> torch.Tensor:
    """Features with φ in {0, 1e-12, 1e-8, 1e-4, just below/above the Taylor switch, 0.3} and random θ."""
    feat = random_features(spec, (batch,), 0).repeat(7, *[1] * 2)
    phis = torch.tensor([0.0, 1e-12, 1e-8, 1e-4, 0.0999, 0.1001, 0.3], dtype=F64).repeat_interleave(batch)
    rho = feat[..., :2]
    norm = rho.norm(dim=-1, keepdim=True)
    radius = torch.tensor([s.radius for s in spec.segments], dtype=F64)[:, None]
    feat[..., :2] = rho / norm * phis[:, None, None] * radius
    return feat


def pk_chain(twists: list[bool]):
    return pk.build_serial_chain_from_urdf(urdf_chain_string(twists), urdf_end_link(twists)).to(dtype=F64)


def pk_joint_values(spec: RobotSpec, feat: torch.Tensor) -> torch.Tensor:
    """(B, m, 4) features → (B, J) joint values of the equivalent rigid chain (arc params via atan2)."""
    cols = []
    for k, seg in enumerate(spec.segments):
        rho = feat[:, k, :2]
        theta = torch.atan2(rho[:, 1], rho[:, 0])
        phi = rho.norm(dim=-1) / seg.radius
        beta = feat[:, k, 2] if seg.extends else torch.full_like(phi, seg.length)
        alpha = feat[:, k, 3] if seg.twists else torch.zeros_like(phi)
        cols += chain_joint_values(theta, phi, beta, alpha, seg.twists)
    return torch.stack(cols, dim=-1)


# ---------------------------------------------------------------- classic arc


@FAST
@given(robots(), seeds)
def test_forward_kinematics_matches_classic_arc(spec, seed):
    feat = random_features(spec, (6,), seed)
    tip = forward_kinematics(spec, feat)
    per_seg = segment_poses(spec, feat)
    assert tip.shape == (6, 4, 4) and per_seg.shape == (6, spec.num_segments, 4, 4)
    for b in range(6):
        f = feat[b].numpy()
        assert np.allclose(tip[b].numpy(), classic_forward_kinematics(spec, f), atol=1e-12, rtol=0)
        for k in range(spec.num_segments):
            theta, phi, beta, alpha = arc_parameters(spec, f, k)
            ref = np.eye(4)
            ref[:3, :3] = rot_z(alpha)
            assert np.allclose(per_seg[b, k].numpy(), ref @ classic_arc(theta, phi, beta), atol=1e-12, rtol=0)


@pytest.mark.parametrize("seg_type", ["0", "I", "II", "III"])
def test_single_segment_near_straight_matches_classic_arc(seg_type):
    spec = one_segment(seg_type)
    feat = straight_and_near_straight(spec)
    tip = forward_kinematics(spec, feat)
    for b in range(feat.shape[0]):
        ref = classic_forward_kinematics(spec, feat[b].numpy())
        assert np.allclose(tip[b].numpy(), ref, atol=1e-13, rtol=0)


def test_rotation_is_proper_orthonormal():
    spec = RobotSpec.from_yaml(next(p for p in ROBOT_CONFIGS if p.stem == "tdcr_3seg_coupled"))
    tip = forward_kinematics(spec, random_features(spec, (100,), 4, bend_scale=2.0))
    rot = tip[..., :3, :3]
    assert torch.allclose(rot @ rot.mT, torch.eye(3, dtype=F64).expand_as(rot), atol=1e-13)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(100, dtype=F64), atol=1e-13)
    assert torch.equal(tip[..., 3, :], torch.tensor([0, 0, 0, 1.0], dtype=F64).expand(100, 4))


def test_bending_coefficients_match_closed_form_both_branches():
    phi = torch.tensor([1e-6, 0.01, 0.09, 0.0999, 0.1001, 0.2, 1.0, 3.0], dtype=F64)
    s, f = bending_coefficients(phi**2)
    assert torch.allclose(s, torch.sin(phi) / phi, atol=0, rtol=1e-14)
    assert torch.allclose(f, 2 * (torch.sin(phi / 2) / phi) ** 2, atol=0, rtol=1e-13)   # 1 − cos φ = 2 sin²(φ/2)
    s0, f0 = bending_coefficients(torch.zeros(1, dtype=F64))
    assert s0.item() == 1.0 and f0.item() == 0.5


# ---------------------------------------------------------------- pytorch_kinematics rigid chain


@pytest.mark.parametrize("seg_type", ["0", "I", "II", "III"])
def test_single_segment_matches_pytorch_kinematics_chain(seg_type):
    spec = one_segment(seg_type, limits={"bend": 3.0})
    feat = torch.cat([random_features(spec, (64,), 1), straight_and_near_straight(spec)[8:]])
    chain = pk_chain([spec.segments[0].twists])
    ref = chain.forward_kinematics(pk_joint_values(spec, feat)).get_matrix()
    ours = forward_kinematics(spec, feat)
    assert (ours - ref).abs().max() <= 1e-12


@FAST
@given(robots(), seeds)
def test_multi_segment_matches_pytorch_kinematics_chain(spec, seed):
    feat = random_features(spec, (16,), seed)
    twists = [s.twists for s in spec.segments]
    chain = pk_chain(twists)
    ref = chain.forward_kinematics(pk_joint_values(spec, feat)).get_matrix()
    assert (forward_kinematics(spec, feat) - ref).abs().max() <= 1e-12
    # every segment tip, too: the chain's frame after each block
    frames = chain.forward_kinematics(pk_joint_values(spec, feat), end_only=False)
    tips = segment_tip_poses(spec, feat)
    end = 0
    for k, tw in enumerate(twists):
        end += 5 + tw
        assert (tips[:, k] - frames[f"link{end}"].get_matrix()).abs().max() <= 1e-12


# ---------------------------------------------------------------- backbone points


@FAST
@given(robots(max_segments=2), seeds, st.integers(1, 6))
def test_backbone_points_on_the_arcs(spec, seed, per_segment):
    feat = random_features(spec, (3,), seed)
    pts = backbone_points(spec, feat, points_per_segment=per_segment)
    assert pts.shape == (3, 1 + spec.num_segments * per_segment, 3)
    for b in range(3):
        ref = reference_backbone(spec, feat[b].numpy(), per_segment)
        assert np.allclose(pts[b, 0].numpy(), 0.0, atol=0)
        assert np.allclose(pts[b].numpy(), ref, atol=1e-12, rtol=0)
    tips = segment_tip_poses(spec, feat)[..., :3, 3]
    tol = roundoff_tol(F64, float(tips.abs().max()))
    assert torch.allclose(pts[:, per_segment::per_segment], tips, atol=tol, rtol=0)


def test_backbone_points_rejects_bad_count():
    spec = one_segment()
    with pytest.raises(ValueError, match="points_per_segment"):
        backbone_points(spec, random_features(spec, (), 0), points_per_segment=0)


# ---------------------------------------------------------------- analytic IK


@pytest.mark.parametrize("seg_type", ["0", "I"])
def test_analytic_ik_inverts_fk(seg_type):
    spec = one_segment(seg_type, limits={"bend": 3.0})
    feat = torch.cat([random_features(spec, (200,), 9), straight_and_near_straight(spec)])
    pos = forward_kinematics(spec, feat)[..., :3, 3]
    est = analytic_inverse_kinematics(spec, pos)
    assert est.shape == feat.shape
    assert (est - feat).abs().max() <= 1e-10
    assert (forward_kinematics(spec, est)[..., :3, 3] - pos).abs().max() <= 1e-13


def test_analytic_ik_exactly_straight_is_finite():
    spec = one_segment("I")
    pos = torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, 0.09]], dtype=F64)
    est = analytic_inverse_kinematics(spec, pos)
    assert torch.allclose(est[:, 0], torch.tensor([[0, 0, 0.1, 0], [0, 0, 0.09, 0]], dtype=F64), rtol=0,
                          atol=roundoff_tol(F64, 0.1))


@pytest.mark.parametrize("desc", [
    {"segments": [{"type": "II", "length": 0.1, "radius": 0.008, "joints": 3}]},
    {"segments": [{"type": "0", "length": 0.1, "radius": 0.008, "joints": 3}] * 2},
])
def test_analytic_ik_rejects_unsupported_robots(desc):
    with pytest.raises(ValueError, match="spec"):
        analytic_inverse_kinematics(RobotSpec.from_dict(desc), torch.zeros(3, dtype=F64))


# ---------------------------------------------------------------- autograd


def mixed_robot() -> RobotSpec:
    return RobotSpec.from_dict({"segments": [
        {"type": "III", "length": 0.1, "radius": 0.008, "joints": 3},
        {"type": "0", "length": 0.08, "radius": 0.006, "joint_angles": [0, 2.2, 4.0],
         "joint_radii": [0.005, 0.007, 0.006]},
        {"type": "II", "length": 0.07, "radius": 0.006, "joints": 4}]})


@pytest.mark.parametrize("straight", [False, True], ids=["generic", "straight"])
def test_gradcheck_forward_kinematics_and_backbone(straight):
    spec = mixed_robot()
    feat = random_features(spec, (2,), 5, straight=straight).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: forward_kinematics(spec, f), (feat,))
    assert torch.autograd.gradcheck(lambda f: backbone_points(spec, f, 3), (feat,))
    grad, = torch.autograd.grad(forward_kinematics(spec, feat).sum(), feat)
    assert torch.isfinite(grad).all()


def test_gradient_at_straight_is_finite_and_correct():
    """d(tip x)/d ρ_re at ρ = 0 equals β/(2d) (x = β·u_x·f, f(0) = 1/2, u = ρ/d)."""
    spec = one_segment("I")
    feat = torch.tensor([[[0.0, 0.0, 0.1, 0.0]]], dtype=F64, requires_grad=True)
    grad, = torch.autograd.grad(forward_kinematics(spec, feat)[..., 0, 3].sum(), feat)
    assert torch.isfinite(grad).all()
    assert grad[0, 0, 0].item() == pytest.approx(0.1 / (2 * 0.008), rel=1e-12)
    assert grad[0, 0, 1].item() == 0.0


@pytest.mark.parametrize("seg_type", ["0", "I"])
@pytest.mark.parametrize("where", ["generic", "straight", "near-straight"])
def test_gradcheck_analytic_ik(seg_type, where):
    spec = one_segment(seg_type)
    pos = {"generic": [[0.02, -0.01, 0.09], [-0.03, 0.005, 0.08]],
           "straight": [[0.0, 0.0, 0.1], [0.0, 0.0, 0.095]],
           "near-straight": [[1e-9, -2e-9, 0.1], [3e-5, 1e-5, 0.1]]}[where]
    pos = torch.tensor(pos, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: analytic_inverse_kinematics(spec, p), (pos,))


# ---------------------------------------------------------------- batching, dtype


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_leading_batch_dims(batch):
    spec = mixed_robot()
    feat = random_features(spec, batch, 2)
    assert forward_kinematics(spec, feat).shape == (*batch, 4, 4)
    assert segment_tip_poses(spec, feat).shape == (*batch, 3, 4, 4)
    assert backbone_points(spec, feat, 4).shape == (*batch, 13, 3)
    ik_spec = one_segment("I")
    assert analytic_inverse_kinematics(ik_spec, torch.ones(*batch, 3, dtype=F64) * 0.03).shape == (*batch, 1, 4)


def test_batched_equals_per_sample_loop():
    spec = mixed_robot()
    feat = random_features(spec, (2, 3), 8)
    tip, pts = forward_kinematics(spec, feat), backbone_points(spec, feat, 5)
    ik_spec = one_segment("I")
    pos = forward_kinematics(ik_spec, random_features(ik_spec, (2, 3), 8))[..., :3, 3]
    ik = analytic_inverse_kinematics(ik_spec, pos)
    tol = roundoff_tol(F64, 1.0)        # poses, points [m] and angles [rad] are all O(1) here
    for i in range(2):
        for j in range(3):
            assert torch.allclose(forward_kinematics(spec, feat[i, j]), tip[i, j], atol=tol, rtol=0)
            assert torch.allclose(backbone_points(spec, feat[i, j], 5), pts[i, j], atol=tol, rtol=0)
            assert torch.allclose(analytic_inverse_kinematics(ik_spec, pos[i, j]), ik[i, j], atol=tol, rtol=0)


def test_float32_follows_input_and_is_accurate():
    spec = mixed_robot()
    feat = random_features(spec, (256,), 6)
    f32 = feat.float()
    for fn in (lambda f: forward_kinematics(spec, f), lambda f: backbone_points(spec, f, 4)):
        out32, out64 = fn(f32), fn(feat)
        assert out32.dtype == torch.float32 and out32.device == f32.device
        assert (out32.double() - out64).abs().max() <= 1e-6
    ik_spec = one_segment("I")
    pos = forward_kinematics(ik_spec, random_features(ik_spec, (256,), 6))[..., :3, 3].float()
    assert analytic_inverse_kinematics(ik_spec, pos).dtype == torch.float32


# ---------------------------------------------------------------- invalid inputs


def assert_names_problem(msg: str, kind: str, expected: str, shape) -> None:
    """Shape errors name the expected and received shapes; NaN/inf errors say 'finite' and the shape."""
    assert str(tuple(shape)) in msg, msg
    if kind in ("nan", "inf"):
        assert "finite" in msg and "NaN/inf" in msg, msg
    else:
        assert f"expected shape {expected}" in msg, msg


@pytest.mark.parametrize("kind", ["nan", "inf", "shape", "missing-dim"])
def test_kinematics_reject_bad_tensors(kind):
    spec = mixed_robot()
    good = random_features(spec, (2,), 0)
    x = {"nan": good.clone().index_fill_(0, torch.tensor([1]), math.nan),
         "inf": good.clone().index_fill_(0, torch.tensor([0]), -math.inf),
         "shape": torch.zeros(2, 3, 5, dtype=F64),
         "missing-dim": torch.zeros(4, dtype=F64)}[kind]
    for fn in (forward_kinematics, backbone_points, segment_poses, segment_tip_poses):
        with pytest.raises(ValueError) as err:
            fn(spec, x)
        assert_names_problem(str(err.value), kind, "(..., 3, 4)", x.shape)
    ik_spec = one_segment("0")
    pos = {"nan": torch.tensor([0.0, math.nan, 0.1]), "inf": torch.tensor([math.inf, 0.0, 0.1]),
           "shape": torch.zeros(2, 4), "missing-dim": torch.tensor(0.1)}[kind].double()
    with pytest.raises(ValueError) as err:
        analytic_inverse_kinematics(ik_spec, pos)
    assert_names_problem(str(err.value), kind, "(..., 3)", pos.shape)


# ---------------------------------------------------------------- torch.export


def test_torch_export_matches_eager_and_does_not_poison_eager_calls():
    """Regression: a tensor cache filled while export traced returned FakeTensors to later eager calls."""
    spec = one_segment("III")

    class Kinematics(torch.nn.Module):
        def forward(self, f):
            return forward_kinematics(spec, f)

    feat = random_features(spec, (4,), 12)
    exported = torch.export.export(Kinematics(), (feat,))
    eager = forward_kinematics(spec, feat)
    assert type(eager) is torch.Tensor
    for b in range(4):
        assert np.allclose(eager[b].numpy(), classic_forward_kinematics(spec, feat[b].numpy()), atol=1e-12)
    other = random_features(spec, (4,), 13)
    assert torch.allclose(exported.module()(other), forward_kinematics(spec, other), atol=roundoff_tol(F64), rtol=0)


# --------------------------------------------------------------------------------------------------
# Closed-form Jacobian of the CC FK (the kernel's tangents and chain rule) against reverse-mode autodiff
# --------------------------------------------------------------------------------------------------


def _random_features(spec: RobotSpec, n: int, seed: int, straight: bool = False) -> torch.Tensor:
    from dacr_learn.data import sample_features
    feats = sample_features(spec, n, torch.Generator().manual_seed(seed), dtype=F64)
    if straight:
        feats[..., :2] = 0.0
    return feats


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "hetero_4seg_types", "type3", "asymmetric"])
@pytest.mark.parametrize("straight", [False, True])
def test_cc_pose_and_jacobian_is_reverse_mode_autodiff(robot, straight):
    from dacr_learn.kinematics import cc_pose_and_jacobian
    from dacr_learn.lie import twist_jacobian
    spec = RobotSpec.from_yaml(ROBOT_CONFIGS[0].parent / f"{robot}.yaml")
    feats = _random_features(spec, 6, 0, straight)
    pose, jac = cc_pose_and_jacobian(spec, feats)
    dpose = torch.func.vmap(torch.func.jacrev(lambda f: forward_kinematics(spec, f)))(feats)   # (6, 4, 4, m, 4)
    expected = twist_jacobian(pose, dpose.flatten(-2)).unflatten(-1, (spec.num_segments, 4))
    assert (pose - forward_kinematics(spec, feats)).abs().max() <= roundoff_tol(F64, spec.total_length)
    assert (jac - expected).abs().max() <= roundoff_tol(F64, 10.0 * spec.total_length / min(
        s.radius for s in spec.segments))


def test_forward_kinematics_runs_under_torch_func_transforms():
    spec = RobotSpec.from_yaml(ROBOT_CONFIGS[0].parent / "type1.yaml")
    feats = _random_features(spec, 3, 1)
    jac = torch.func.vmap(torch.func.jacfwd(lambda f: forward_kinematics(spec, f)))(feats)
    assert jac.shape == (3, 4, 4, 1, 4) and torch.isfinite(jac).all()
