"""SE(3) / se(3) in closed form, batched and differentiable: the one place the twist maths lives.

A twist ξ = (v, ω) (..., 6) [m, rad] has the matrix ξ^ = [[ω^, v], [0, 0]] and the exponential

    exp(ξ^) = [[R, p], [0, 1]],  R = I + s·ω^ + f·ω^²,  p = (I + f·ω^ + g·ω^²)·v,
    s = sin φ/φ,  f = (1 − cos φ)/φ²,  g = (φ − sin φ)/φ³,  φ = ‖ω‖,

with s, f, g written as functions of φ² that are finite, with finite derivatives, at φ = 0 (Taylor
polynomials below :data:`TAYLOR_BELOW`). A constant-curvature segment is the exponential of a twist that
is linear in its Clarke coordinates (docs/design.md §2), so the CC kinematics (:mod:`.kinematics`), the
compositional FK (:mod:`.compositional`) and the folded hardware inference modules
(:mod:`.hardware.deploy`) all build on these functions. Pure torch, any leading batch dims.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "TAYLOR_BELOW", "bending_coefficients", "bending_coefficients_and_derivatives", "chain_products",
    "exp_of_twist_matrix", "hat", "hat_map", "pose_from_parts", "third_coefficient", "twist_exp",
    "roll_z", "twist_exp_and_tangent", "vee",
]

TAYLOR_BELOW = 1e-2   # φ² below which s, f, g and their derivatives are Taylor polynomials (exact to ~1e-14)


def bending_coefficients(phi_sq: Tensor) -> tuple[Tensor, Tensor]:
    """s = sin φ/φ and f = (1 − cos φ)/φ² as functions of φ² (..., ), finite with finite gradients at 0.

    f is evaluated as 2·(sin(φ/2)/φ)², which has no cancellation (accurate in float32 too).
    """
    small = phi_sq < TAYLOR_BELOW
    phi = torch.sqrt(torch.where(small, 1.0, phi_sq))
    inv_phi = 1 / phi
    half = torch.sin(0.5 * phi) * inv_phi
    s_big, f_big = torch.sin(phi) * inv_phi, 2 * half * half
    y = torch.where(small, phi_sq, 0.0)
    # Horner forms of s = 1 − y/6 + y²/120 − y³/5040 + y⁴/362880, f = 1/2 − y/24 + y²/720 − y³/40320 + y⁴/3628800
    s_small = (((y / 362880 - 1 / 5040) * y + 1 / 120) * y - 1 / 6) * y + 1
    f_small = (((y / 3628800 - 1 / 40320) * y + 1 / 720) * y - 1 / 24) * y + 0.5
    return torch.where(small, s_small, s_big), torch.where(small, f_small, f_big)


def bending_coefficients_and_derivatives(phi_sq: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """s, f (:func:`bending_coefficients`) and their derivatives ds/dφ², df/dφ² (..., ) (Taylor branch
    near 0, below the same threshold)."""
    s, f = bending_coefficients(phi_sq)
    small = phi_sq < TAYLOR_BELOW
    phi_sq_big = torch.where(small, 1.0, phi_sq)
    y = torch.where(small, phi_sq, 0.0)
    ds_small = ((4 * y / 362880 - 3 / 5040) * y + 2 / 120) * y - 1 / 6
    df_small = ((4 * y / 3628800 - 3 / 40320) * y + 2 / 720) * y - 1 / 24
    ds_big = (torch.cos(torch.sqrt(phi_sq_big)) - s) / (2 * phi_sq_big)   # s, f of the big branch where used
    df_big = (s - 2 * f) / (2 * phi_sq_big)
    return s, f, torch.where(small, ds_small, ds_big), torch.where(small, df_small, df_big)


def third_coefficient(phi_sq: Tensor, s: Tensor) -> Tensor:
    """g = (φ − sin φ)/φ³ = (1 − s)/φ² as a function of φ² (..., ) and s = sin φ/φ, finite with finite
    gradients at 0."""
    small = phi_sq < TAYLOR_BELOW
    y = torch.where(small, phi_sq, 0.0)
    g_small = (((-y / 39916800 + 1 / 362880) * y - 1 / 5040) * y + 1 / 120) * -y + 1 / 6
    return torch.where(small, g_small, (1 - s) / torch.where(small, 1.0, phi_sq))


def exp_coefficients_and_derivatives(phi_sq: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(s, f, g, ds, df, dg) of φ² (...): the coefficients of exp of a twist (:func:`twist_exp`) and their
    φ²-derivatives (Taylor polynomials below ``TAYLOR_BELOW``)."""
    s, f, ds, df = bending_coefficients_and_derivatives(phi_sq)
    g = third_coefficient(phi_sq, s)
    small = phi_sq < TAYLOR_BELOW
    y = torch.where(small, phi_sq, 0.0)
    dg_small = ((4 * y / 39916800 - 3 / 362880) * y + 2 / 5040) * y - 1 / 120
    dg = torch.where(small, dg_small, (-ds - g) / torch.where(small, 1.0, phi_sq))
    return s, f, g, ds, df, dg


def hat(w: Tensor) -> Tensor:
    """Skew matrices ω^ (..., 3, 3) of vectors ω (..., 3): ω^·x = ω × x."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack([zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0],
                        -w[..., 1], w[..., 0], zero], dim=-1).unflatten(-1, (3, 3))


def vee(w_hat: Tensor) -> Tensor:
    """ω (..., 3) of skew matrices ω^ (..., 3, 3) (the inverse of :func:`hat`; the skew part is read)."""
    return 0.5 * torch.stack([w_hat[..., 2, 1] - w_hat[..., 1, 2], w_hat[..., 0, 2] - w_hat[..., 2, 0],
                              w_hat[..., 1, 0] - w_hat[..., 0, 1]], dim=-1)


def pose_from_parts(rotation: Tensor, position: Tensor, bottom: Tensor | None = None) -> Tensor:
    """Homogeneous pose (..., 4, 4) from rotation (..., 3, 3) and position (..., 3).

    ``bottom``: the row (0, 0, 0, 1) as a (1, 4) tensor of the right dtype/device, if the caller
    keeps one (the exported inference modules hold it as a buffer); built here otherwise.
    """
    top = torch.cat([rotation, position.unsqueeze(-1)], dim=-1)
    if bottom is None:
        bottom = torch.zeros_like(top[..., :1, :])
        bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom.expand(*top.shape[:-2], 1, 4)], dim=-2)


def hat_map(dtype: torch.dtype = torch.float64) -> Tensor:
    """(6, 16): the linear map ξ = (v, ω) ↦ ξ^ = [[ω^, v], [0, 0]] flattened row-major."""
    basis = torch.eye(6, dtype=dtype)
    return pose_from_parts(hat(basis[:, 3:]), basis[:, :3], basis.new_zeros(1, 4)).flatten(-2)


def twist_exp(xi: Tensor) -> Tensor:
    """exp of se(3) twists: (..., 6) = (v [m], ω [rad]) → homogeneous transforms (..., 4, 4).

    Closed form (module docstring); equals torch.linalg.matrix_exp of ξ^ (tested) at a fraction of its cost.
    """
    v, w = xi[..., :3], xi[..., 3:]
    phi_sq = (w * w).sum(-1)
    s, f = bending_coefficients(phi_sq)
    g = third_coefficient(phi_sq, s)
    wv = torch.linalg.cross(w, v)
    p = v + f.unsqueeze(-1) * wv + g.unsqueeze(-1) * torch.linalg.cross(w, wv)
    w_hat = hat(w)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    rot = eye + s[..., None, None] * w_hat + f[..., None, None] * (w_hat @ w_hat)
    return pose_from_parts(rot, p)


def twist_exp_and_tangent(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor]:
    """exp of twists ξ = (v, ω) (..., 6) (:func:`twist_exp`, (..., 4, 4)) and its tangents (..., T, 4, 4)
    along dξ (..., T, 6): the derivative of R = I + s·ω^ + f·ω^², p = v + f·ω×v + g·ω×(ω×v) with s, f, g
    functions of φ² = ‖ω‖² (their φ²-derivatives: Taylor series below the same threshold)."""
    v, w, dv, dw = xi[..., :3], xi[..., 3:], dxi[..., :3], dxi[..., 3:]
    phi_sq = (w * w).sum(-1)
    s, f, g, ds, df, dg = exp_coefficients_and_derivatives(phi_sq)
    dphi = 2 * (w.unsqueeze(-2) * dw).sum(-1)                                              # (..., T)
    at = lambda c: c.unsqueeze(-1)  # noqa: E731   coefficient (...) → (..., T) broadcast
    wv = torch.linalg.cross(w, v)
    dwv = torch.linalg.cross(dw, v.unsqueeze(-2)) + torch.linalg.cross(w.unsqueeze(-2), dv)
    wwv = torch.linalg.cross(w, wv)
    dwwv = torch.linalg.cross(dw, wv.unsqueeze(-2)) + torch.linalg.cross(w.unsqueeze(-2), dwv)
    dp = (dv + (at(df) * dphi).unsqueeze(-1) * wv.unsqueeze(-2) + at(f).unsqueeze(-1) * dwv
          + (at(dg) * dphi).unsqueeze(-1) * wwv.unsqueeze(-2) + at(g).unsqueeze(-1) * dwwv)
    w_hat = hat(w)
    hat2 = w_hat @ w_hat
    rot = torch.eye(3, dtype=xi.dtype, device=xi.device) + s[..., None, None] * w_hat + f[..., None, None] * hat2
    value = pose_from_parts(rot, v + f.unsqueeze(-1) * wv + g.unsqueeze(-1) * wwv)        # = twist_exp(xi)
    w_hat, hat2, dhat = w_hat.unsqueeze(-3), hat2.unsqueeze(-3), hat(dw)
    k = lambda c: c[..., None, None]  # noqa: E731   (..., T) → (..., T, 1, 1)
    drot = (k(at(ds) * dphi) * w_hat + k(at(s)) * dhat + k(at(df) * dphi) * hat2
            + k(at(f)) * (dhat @ w_hat + w_hat @ dhat))
    return value, pose_from_parts(drot, dp, dp.new_zeros(1, 4))


def exp_of_twist_matrix(xi_hat: Tensor) -> Tensor:
    """exp(ξ^) (..., 4, 4) of twist matrices ξ^ (..., 4, 4): I + ξ^ + f·ξ^² + g·ξ^³ (ω^³ = −φ²ω^ makes the
    series collapse; the same map as :func:`twist_exp` in fewer ops, for folded inference modules).
    ‖ω^‖_F = √2·φ; s, f as sinc terms of y = φ/2π, g from the Taylor-guarded (1 − s)/φ²."""
    rot = xi_hat[..., :3, :3]
    phi_sq = 0.5 * (rot * rot).sum((-2, -1))
    y = torch.linalg.vector_norm(rot.flatten(-2), dim=-1) * (0.5 / (torch.pi * 2**0.5))
    g = third_coefficient(phi_sq, torch.sinc(2 * y))
    sq = xi_hat @ xi_hat
    out = torch.addcmul(xi_hat, (0.5 * torch.sinc(y) ** 2)[..., None, None], sq)
    out = torch.addcmul(out, g[..., None, None], sq @ xi_hat)
    return out + torch.eye(4, dtype=xi_hat.dtype)


def chain_products(poses: Tensor) -> Tensor:
    """Cumulative products T⁽¹⁾, T⁽¹⁾T⁽²⁾, …: (..., m, 4, 4) → (..., m, 4, 4)."""
    out = [poses[..., 0, :, :]]
    for j in range(1, poses.shape[-3]):
        out.append(out[-1] @ poses[..., j, :, :])
    return torch.stack(out, dim=-3)


def roll_z(poses: Tensor, alpha: Tensor) -> Tensor:
    """Rz(α)·T: poses (..., 4, 4) rolled by α (...) [rad] about the z axis of the frame they are expressed in
    (rows 0 and 1 rotated pointwise; α = 0 returns the poses' values unchanged)."""
    c, s = torch.cos(alpha)[..., None], torch.sin(alpha)[..., None]
    r0, r1 = poses[..., 0, :], poses[..., 1, :]
    return torch.cat([(c * r0 - s * r1).unsqueeze(-2), (s * r0 + c * r1).unsqueeze(-2), poses[..., 2:, :]], dim=-2)
