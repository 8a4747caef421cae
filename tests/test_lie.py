"""dacr_learn.lie against independent references: torch.linalg.matrix_exp, autograd, float64 gradcheck."""
from __future__ import annotations

import pytest
import torch

from dacr_learn import lie


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
    torch.testing.assert_close((xi @ lie.hat_map()).unflatten(-1, (4, 4)),
                               lie.pose_from_parts(lie.hat(xi[:, 3:]), xi[:, :3], torch.zeros(1, 4, dtype=xi.dtype)))


@pytest.mark.parametrize("scale", [0.0, 1e-5, 0.05, 1.0, 3.0])     # φ = 0, inside and beyond the Taylor branch
def test_twist_exp_and_the_matrix_form_equal_matrix_exp(scale):
    xi = twists(64, scale)
    xi_hat = (xi @ lie.hat_map()).unflatten(-1, (4, 4))
    reference = torch.linalg.matrix_exp(xi_hat)
    torch.testing.assert_close(lie.twist_exp(xi), reference, atol=1e-12, rtol=0)
    torch.testing.assert_close(lie.exp_of_twist_matrix(xi_hat), reference, atol=1e-12, rtol=0)


@pytest.mark.parametrize("scale", [1e-4, 0.05, 2.0])
def test_twist_exp_tangent_is_autograds_directional_derivative(scale):
    xi, dxi = twists(8, scale), twists(8 * 3, 1.0, seed=1).view(8, 3, 6)
    value, tangent = lie.twist_exp_and_tangent(xi, dxi)
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
