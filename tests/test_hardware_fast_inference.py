"""The inference path's closed forms against the library's iterative / generic ones.

- The slack QP by active-set enumeration (:func:`~dacr_learn.hardware.slack.solve_tendon_qp_enumerated`,
  used folded by HardwareFK) against the semi-smooth Newton iteration :func:`solve_tendon_qp` and the
  optimality condition of the energy, in float64 and float32.
- The CC segment pose T = I + sΞ + fΞ² (:func:`~dacr_learn.hardware.deploy.inference.twist_segment_poses`)
  against :func:`~dacr_learn.kinematics.cc_transform`, with finite gradients at zero bending.
- The chained tip and its closed-form ∂tip/∂ρ (:func:`~dacr_learn.hardware.deploy.inference.twist_tip_and_jacobian`)
  against the tip of cc_transform products and autograd's Jacobian of it, straight segments included.
"""
from __future__ import annotations

import pytest
import torch
from conftest import FAST, ROOT, roundoff_tol
from hypothesis import given
from hypothesis import strategies as st

from dacr_learn.hardware.deploy.inference import segment_twists, twist_segment_poses, twist_tip_and_jacobian
from dacr_learn.hardware.slack import SlackAwareEncoder, active_set_gains, solve_tendon_qp, solve_tendon_qp_enumerated
from dacr_learn.kinematics import cc_transform
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
SPECS = {"v4": RobotSpec.from_yaml(ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"),
         "2seg-independent": RobotSpec.from_dict({"name": "two", "routing": "independent", "segments": [
             {"type": "0", "length": 0.08, "radius": 0.005, "joints": 4, "offset": 0.4},
             {"type": "0", "length": 0.07, "radius": 0.004, "joints": 3, "offset": -1.1}]})}


def _problem(spec: RobotSpec, log_c: float, pretension: float, seed: int, n: int = 300):
    """Encoder weights with perturbed radii / rotations and commands (n, N) [m] with many slack tendons."""
    enc = SlackAwareEncoder(spec, compliance=10.0**log_c, pretension=pretension)
    g = torch.Generator().manual_seed(seed)
    m = spec.num_segments
    with torch.no_grad():
        enc.log_radius_scale.copy_(0.1 * torch.randn(m, generator=g, dtype=F64))
        enc.rotation.copy_(0.1 * torch.randn(m, generator=g, dtype=F64))
        x = 4e-3 * torch.randn(n, enc.g_nominal.shape[0], generator=g, dtype=F64) + enc.pretension
        return x, enc.displacement_map(), enc.bend_weights(), 1.0 / enc.path_length


@pytest.mark.parametrize("name", sorted(SPECS))
@FAST
@given(log_c=st.floats(-8.0, -4.0), pretension=st.floats(0.0, 1e-3), seed=st.integers(0, 2**16))
def test_enumerated_qp_is_the_iterative_solution_and_optimal(name, log_c, pretension, seed):
    x, g, bend_w, tendon_w = _problem(SPECS[name], log_c, pretension, seed)
    rho = solve_tendon_qp_enumerated(x, g, bend_w, tendon_w)
    ref = solve_tendon_qp(x, g, bend_w, tendon_w)
    scale = float(ref.abs().max())
    assert (rho - ref).abs().max() <= roundoff_tol(F64, scale, ulps=4096)
    # independent of both solvers: the energy's gradient bend_w·ρ − Gᵀ W max(0, x − Gρ) vanishes (to the
    # rounding of x − Gρ, weighted)
    stretch = torch.relu(x - rho @ g.mT)
    force_scale = float(tendon_w.max() * x.abs().max() * g.abs().sum(0).max())
    assert (bend_w * rho - (tendon_w * stretch) @ g).abs().max() <= roundoff_tol(F64, force_scale, ulps=1024)
    assert bool((stretch == 0).any()) and bool((stretch > 0).any()), "slack and stretched tendons are exercised"


def test_enumerated_qp_in_float32_is_the_float64_solution_to_float32_rounding():
    x, g, bend_w, tendon_w = _problem(SPECS["v4"], -6.0, 1e-4, 3, n=2000)
    ref = solve_tendon_qp(x, g, bend_w, tendon_w)
    got = solve_tendon_qp_enumerated(x.float(), g, bend_w, tendon_w)
    assert got.dtype == torch.float32
    assert (got.double() - ref).abs().max() <= roundoff_tol(torch.float32, float(ref.abs().max()), ulps=1024)


def test_enumerated_qp_is_differentiable_in_the_commands():
    x, g, bend_w, tendon_w = _problem(SPECS["2seg-independent"], -6.0, 2e-4, 5, n=6)
    assert torch.autograd.gradcheck(lambda v: solve_tendon_qp_enumerated(v, g, bend_w, tendon_w),
                                    (x.requires_grad_(True),), eps=1e-9, atol=1e-7)


def test_active_set_gains_reject_too_many_tendons():
    g = torch.ones(13, 2, dtype=F64)
    with pytest.raises(ValueError, match="at most 12 tendons"):
        active_set_gains(g, torch.ones(2, dtype=F64), torch.ones(13, dtype=F64))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_segment_pose_from_twist_is_cc_transform(dtype):
    g = torch.Generator().manual_seed(0)
    radius, length = torch.tensor([0.005, 0.004, 0.0045], dtype=F64), torch.tensor([0.08, 0.07, 0.06], dtype=F64)
    rho = 0.004 * (2 * torch.rand(400, 3, 2, generator=g, dtype=F64) - 1)
    rho[:50] *= 1e-6                                           # nearly straight
    rho[50:60] = 0.0                                           # straight
    constants = {k: v.to(dtype) for k, v in segment_twists(radius, length).items()}
    got = twist_segment_poses(rho.to(dtype), **constants)
    ref = cc_transform(rho / radius.unsqueeze(-1), length.expand(400, 3))
    assert (got.double() - ref).abs().max() <= roundoff_tol(dtype, 1.0, ulps=16)


def test_segment_pose_gradient_is_finite_and_right_at_zero_bending():
    radius, length = torch.tensor([0.005], dtype=F64), torch.tensor([0.08], dtype=F64)
    constants = segment_twists(radius, length)

    def pose(rho):
        return twist_segment_poses(rho, **constants)

    def reference(rho):
        return cc_transform(rho / radius.unsqueeze(-1), length)

    for rho in (torch.zeros(1, 2, dtype=F64), torch.tensor([[1e-3, -2e-3]], dtype=F64)):
        got = torch.autograd.functional.jacobian(pose, rho)
        ref = torch.autograd.functional.jacobian(reference, rho)
        assert bool(torch.isfinite(got).all())
        assert (got - ref).abs().max() <= roundoff_tol(F64, float(ref.abs().max()), ulps=1024)


def test_tip_jacobian_in_closed_form_is_autograds_of_the_cc_chain():
    """Three segments, a base pose and a marker offset; ρ with straight (0) and nearly straight (1e-9 m)
    segments, where s, f and their derivatives take the Taylor branch."""
    g = torch.Generator().manual_seed(1)
    radius, length = torch.tensor([0.005, 0.004, 0.0045], dtype=F64), torch.tensor([0.08, 0.07, 0.06], dtype=F64)
    angle = torch.tensor(0.3, dtype=F64)
    base = torch.eye(4, dtype=F64)
    base[:2, :2] = torch.tensor([[angle.cos(), -angle.sin()], [angle.sin(), angle.cos()]])
    base[:3, 3] = torch.tensor([0.01, -0.02, 0.3], dtype=F64)
    marker = torch.tensor([0.004, -0.002, 0.01, 1.0], dtype=F64)
    constants = segment_twists(radius, length)
    rho = 0.004 * (2 * torch.rand(6, 3, 2, generator=g, dtype=F64) - 1)
    rho[0, 1] = 0.0
    rho[1, 0] = 1e-9
    rho[2] = 0.0

    def reference_tip(r):                                      # base · T₁ T₂ T₃ · marker with cc_transform
        chain = base
        for k in range(3):
            chain = chain @ cc_transform(r[k] / radius[k], length[k])
        return (chain @ marker)[:3]

    tip, jac = twist_tip_and_jacobian(rho, constants["twist_map"], constants["twist_offset"], radius,
                                      constants["eye4"], base, marker)
    for b in range(rho.shape[0]):
        ref_tip = reference_tip(rho[b])
        ref_jac = torch.autograd.functional.jacobian(reference_tip, rho[b])             # (3, m, 2)
        assert (tip[b] - ref_tip).abs().max() <= roundoff_tol(F64, 1.0, ulps=64)
        assert bool(torch.isfinite(jac[b]).all())
        tol = roundoff_tol(F64, float(ref_jac.abs().max()), ulps=1024)
        assert (jac[b].permute(2, 0, 1) - ref_jac).abs().max() <= tol
