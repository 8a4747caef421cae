"""dacr_learn.lie against independent references: torch.linalg.matrix_exp, autograd, float64 gradcheck, the CC arc."""
from __future__ import annotations

import lie_testkit as testkit
import pytest
import torch
from conftest import roundoff_tol

from dacr_learn import lie
from dacr_learn.kinematics import cc_transform
from dacr_learn.lie import twist_exp

F64 = torch.float64


def twists(n: int, scale: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=torch.float64)
    xi[:, 3:] *= scale
    return xi


def test_hat_vee_are_inverse_and_hat_is_the_cross_product():
    w, x = torch.randn(5, 3, dtype=torch.float64), torch.randn(5, 3, dtype=torch.float64)
    torch.testing.assert_close(lie.vee(lie.hat(w)), w)
    torch.testing.assert_close((lie.hat(w) @ x.unsqueeze(-1)).squeeze(-1), torch.linalg.cross(w, x))
    xi = twists(4, 1.0)
    torch.testing.assert_close((xi @ testkit.hat_map()).unflatten(-1, (4, 4)),
                               lie.pose_from_parts(lie.hat(xi[:, 3:]), xi[:, :3], torch.zeros(1, 4, dtype=xi.dtype)))


@pytest.mark.parametrize("scale", [1e-4, 0.05, 2.0])
def test_twist_exp_tangent_is_autograds_directional_derivative(scale):
    xi, dxi = twists(8, scale), twists(8 * 3, 1.0, seed=1).view(8, 3, 6)
    value, tangent = testkit.twist_exp_and_tangent(xi, dxi)
    expected = torch.stack([torch.func.jvp(lie.twist_exp, (xi,), (dxi[:, t],))[1] for t in range(3)], dim=1)
    torch.testing.assert_close(value, lie.twist_exp(xi))
    torch.testing.assert_close(tangent, expected, atol=1e-12, rtol=0)


def test_coefficient_derivatives_are_autograds_on_both_branches():
    phi_sq = torch.tensor([0.0, 1e-6, 5e-3, 0.0099, 0.0101, 0.5, 4.0], dtype=torch.float64, requires_grad=True)
    s, f, ds, df = lie.bending_coefficients_and_derivatives(phi_sq)
    ds_auto, = torch.autograd.grad(s.sum(), phi_sq, retain_graph=True)
    df_auto, = torch.autograd.grad(f.sum(), phi_sq)
    torch.testing.assert_close(ds, ds_auto, atol=1e-12, rtol=0)
    torch.testing.assert_close(df, df_auto, atol=1e-12, rtol=0)


def test_twist_exp_gradcheck_float64():
    for scale in (0.0, 1e-3, 1.5):
        xi = twists(3, scale).requires_grad_(True)
        assert torch.autograd.gradcheck(lie.twist_exp, (xi,))


def test_chain_products_are_the_running_products():
    poses = lie.twist_exp(twists(4 * 3, 1.0).view(4, 3, 6))
    chained = lie.chain_products(poses)
    torch.testing.assert_close(chained[:, 2], poses[:, 0] @ poses[:, 1] @ poses[:, 2])
    torch.testing.assert_close(chained[:, 0], poses[:, 0])
    assert torch.equal(lie.chain_products(poses, tip_only=True), chained[:, -1])


def test_twist_jacobian_reads_the_angular_velocity_of_a_rotating_pose():
    """T(t) = exp(t·ξ^)·P: dT/dt at t = 0 is ξ^·P (one column, k = 1): the tip point moves at v + ω × p, the
    frame turns at ω."""
    xi, pose = twists(5, 1.0, seed=3), lie.twist_exp(twists(5, 1.0, seed=4))
    dpose = (lie.pose_from_parts(lie.hat(xi[:, 3:]), xi[:, :3], torch.zeros(1, 4, dtype=F64)) @ pose).unsqueeze(-1)
    expected = torch.cat([xi[:, :3] + torch.linalg.cross(xi[:, 3:], pose[:, :3, 3]), xi[:, 3:]], dim=-1)
    torch.testing.assert_close(lie.twist_jacobian(pose, dpose)[..., 0], expected, atol=1e-14, rtol=0)


# --------------------------------------------------------------------------------------------------
# Twist exponential: against matrix_exp of the 4×4 twist matrix, the CC arc, autodiff
# --------------------------------------------------------------------------------------------------


def hat(xi: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    v, w = xi[..., :3], xi[..., 3:]
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    out[..., :3, 3] = v
    return out


@pytest.mark.parametrize("scale", [0.0, 1e-4, 0.05, 0.3, 1.0, 3.0])
def test_twist_exp_equals_matrix_exp(scale):
    g = torch.Generator().manual_seed(1)
    xi = torch.randn(200, 6, generator=g, dtype=F64)
    xi[:, 3:] *= scale
    assert torch.allclose(twist_exp(xi), torch.linalg.matrix_exp(hat(xi)), rtol=0, atol=roundoff_tol(F64, 10.0))


def test_twist_exp_of_cc_twist_is_the_cc_arc():
    g = torch.Generator().manual_seed(2)
    u, beta = torch.randn(100, 2, generator=g, dtype=F64), 0.05 + torch.rand(100, generator=g, dtype=F64)
    xi = torch.stack([0 * beta, 0 * beta, beta, -u[:, 1], u[:, 0], 0 * beta], dim=-1)
    assert torch.allclose(twist_exp(xi), cc_transform(u, beta), rtol=0, atol=roundoff_tol(F64))


@pytest.mark.parametrize("scale", [0.0, 0.05, 1.0])       # 0 and 0.05: the Taylor branch of g
def test_twist_exp_gradcheck(scale):
    xi = (torch.randn(4, 6, generator=torch.Generator().manual_seed(3), dtype=F64) * scale).requires_grad_()
    assert torch.autograd.gradcheck(twist_exp, (xi,))


@pytest.mark.parametrize("scale", [0.02, 1.5])            # the Taylor branch (φ² < 1e-2) and the closed form
def test_twist_exp_tangent_matches_forward_mode_autodiff(scale):
    xi = scale * torch.randn(16, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    value, tangent = testkit.twist_exp_and_tangent(xi, torch.eye(6, dtype=torch.float64).expand(16, 6, 6))
    ref = torch.func.vmap(torch.func.jacfwd(twist_exp))(xi).permute(0, 3, 1, 2)    # (16, 6, 4, 4)
    assert torch.equal(value, twist_exp(xi))
    assert (tangent - ref).abs().max() <= roundoff_tol(torch.float64, float(ref.abs().max()))


# --------------------------------------------------------------------------------------------------
# The kernel's spatial tangents, roll and chain rule against forward/reverse-mode autodiff
# --------------------------------------------------------------------------------------------------


def spatial(pose: torch.Tensor, dpose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(b = vee(dR·Rᵀ), dp) of a pose (..., 4, 4) and its derivative (..., 4, 4)."""
    return lie.vee(dpose[..., :3, :3] @ pose[..., :3, :3].mT), dpose[..., :3, 3]


@pytest.mark.parametrize("scale", [0.0, 1e-4, 0.05, 0.3, 2.5])   # φ = 0, the Taylor branch, the closed form
def test_twist_exp_and_tangents_are_forward_mode_autodiff(scale):
    xi, dxi = twists(12, scale, seed=4), twists(12 * 5, 1.0, seed=5).view(12, 5, 6)
    pose, ang, lin = testkit.twist_exp_and_tangents(xi, dxi)
    assert torch.equal(pose, twist_exp(xi))
    for t in range(5):
        b, dp = spatial(pose, torch.func.jvp(twist_exp, (xi,), (dxi[:, t],))[1])
        assert (ang[:, t] - b).abs().max() <= roundoff_tol(F64, 10.0)
        assert (lin[:, t] - dp).abs().max() <= roundoff_tol(F64, 10.0 * (1 + float(xi[:, :3].abs().max())))


def test_roll_z_and_tangents_are_forward_mode_autodiff():
    xi, alpha = twists(6, 1.0, seed=6), torch.linspace(-2.0, 2.0, 6, dtype=F64)
    dxi = torch.cat([twists(6 * 2, 1.0, seed=7).view(6, 2, 6), torch.zeros(6, 1, 6, dtype=F64)], dim=1)
    alpha_row = torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(3, 1)   # direction 2 is the roll angle
    pose, ang, lin = testkit.roll_z_and_tangents(*testkit.twist_exp_and_tangents(xi, dxi), alpha, alpha_row)

    def rolled(x, a):
        return lie.roll_z(twist_exp(x), a)

    assert torch.equal(pose, rolled(xi, alpha))
    for t in range(3):
        direction = (dxi[:, t], alpha_row[t].expand(6))
        b, dp = spatial(pose, torch.func.jvp(rolled, (xi, alpha), direction)[1])
        torch.testing.assert_close(ang[:, t], b, atol=roundoff_tol(F64, 10.0), rtol=0)
        torch.testing.assert_close(lin[:, t], dp, atol=roundoff_tol(F64, 10.0), rtol=0)


@pytest.mark.parametrize("factors", [1, 2, 5])
def test_chain_jacobian_is_reverse_mode_autodiff_of_the_product(factors):
    """J of T_1(x_1)⋯T_n(x_n), each T_k = exp of a twist that moves along 3 directions, against jacrev."""
    xi, dirs = twists(4 * factors, 1.0, seed=8).view(4, factors, 6), twists(factors * 3, 1.0, seed=9)
    dirs = dirs.view(factors, 3, 6)

    def tip(x):                                               # x (factors, 3): coordinates along dirs
        return lie.chain_products(twist_exp(xi_k + (x.unsqueeze(-1) * dirs).sum(-2)))[..., -1, :, :]

    for b in range(4):
        xi_k = xi[b]
        pose, ang, lin = testkit.twist_exp_and_tangents(xi_k, dirs)
        got_tip, jac = testkit.chain_jacobian(pose, ang, lin)
        x0 = torch.zeros(factors, 3, dtype=F64)
        ref = torch.func.jacrev(tip)(x0).flatten(-2)           # (4, 4, factors·3)
        rot = got_tip[:3, :3]
        omega = lie.vee(torch.einsum("ijk,lj->ilk", ref[:3, :3], rot).permute(2, 0, 1))   # (factors·3, 3)
        expected = torch.cat([ref[:3, 3], omega.mT], dim=0)
        torch.testing.assert_close(got_tip, tip(x0), atol=roundoff_tol(F64, 10.0), rtol=0)
        torch.testing.assert_close(jac, expected, atol=roundoff_tol(F64, 100.0), rtol=0)


def test_chain_jacobian_with_a_fixed_base_and_point_is_reverse_mode_autodiff():
    """base · T_1(x_1) T_2(x_2) · Trans(point): the point's velocity and the angular velocity in base's frame."""
    xi, dirs = twists(2, 1.0, seed=10), twists(2 * 3, 1.0, seed=11).view(2, 3, 6)
    base, point = twist_exp(twists(1, 1.0, seed=12)[0]), torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    offset = torch.eye(4, dtype=F64)
    offset[:3, 3] = point

    def tip(x):
        return base @ lie.chain_products(twist_exp(xi + (x.unsqueeze(-1) * dirs).sum(-2)))[-1] @ offset

    pose, ang, lin = testkit.twist_exp_and_tangents(xi, dirs)
    got_tip, jac = testkit.chain_jacobian(pose, ang, lin, base, point)
    x0 = torch.zeros(2, 3, dtype=F64)
    ref = torch.func.jacrev(tip)(x0).flatten(-2)                 # (4, 4, 6)
    omega = lie.vee(torch.einsum("ijk,lj->ilk", ref[:3, :3], got_tip[:3, :3]).permute(2, 0, 1))
    torch.testing.assert_close(got_tip, tip(x0), atol=roundoff_tol(F64, 10.0), rtol=0)
    torch.testing.assert_close(jac, torch.cat([ref[:3, 3], omega.mT], dim=0), atol=roundoff_tol(F64, 100.0), rtol=0)


def test_twist_chain_jacobian_is_the_composition_of_the_tensor_wrappers():
    """The fused product-of-exponentials Jacobian (with rolls and fixed ends) equals twist_exp_and_tangents,
    roll_z_and_tangents and chain_jacobian called one after the other."""
    xi, dxi = twists(2 * 3, 0.7, seed=13).view(2, 3, 6), twists(2 * 3 * 4, 1.0, seed=14).view(2, 3, 4, 6)
    alpha = torch.tensor([[0.3, -1.1, 0.0], [2.0, 0.5, -0.4]], dtype=F64)
    alpha_row = torch.zeros(3, 4, 1, dtype=F64)
    alpha_row[:, 3] = 1.0
    base, point = twist_exp(twists(1, 1.0, seed=15)[0]), torch.tensor([0.1, 0.2, -0.3], dtype=F64)
    poses = testkit.roll_z_and_tangents(*testkit.twist_exp_and_tangents(xi, dxi), alpha, alpha_row)
    tip, jac = lie.twist_chain_jacobian(xi, dxi, alpha, alpha_row, base, point)
    ref_tip, ref_jac = testkit.chain_jacobian(*poses, base, point)
    torch.testing.assert_close(tip, ref_tip, atol=roundoff_tol(F64, 10.0), rtol=0)
    torch.testing.assert_close(jac, ref_jac, atol=roundoff_tol(F64, 100.0), rtol=0)
