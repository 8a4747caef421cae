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


def exp_coefficients(phi_sq: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(s, f, g) of φ² (...): the coefficients of the exponential of a twist (module docstring)."""
    s, f = bending_coefficients(phi_sq)
    return s, f, third_coefficient(phi_sq, s)


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


def _pose_from_entries(rows: list[list[Tensor]], like: Tensor) -> Tensor:
    """(..., 4, 4) homogeneous poses from the 3 × 4 top entries (each broadcastable to ``like``'s shape (...)).

    Written entry by entry into one output tensor: small batched matmuls and last-dim stacking dominate the
    run time on CPU for large batches. Under torch.func transforms (vmap, jacfwd), where writing into a new
    tensor is not allowed, the entries are stacked instead (same values).
    """
    shape = torch.broadcast_shapes(like.shape, *(v.shape for row in rows for v in row))
    if torch._C._functorch.is_functorch_wrapped_tensor(like) or torch.compiler.is_compiling():
        zero = torch.zeros(shape, dtype=like.dtype, device=like.device)
        flat = [v.expand(shape) for row in rows for v in row] + [zero, zero, zero, zero + 1]
        return torch.stack(flat, dim=-1).unflatten(-1, (4, 4))
    out = torch.empty(*shape, 4, 4, dtype=like.dtype, device=like.device)
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            out[..., i, j] = value
    out[..., 3, :3] = 0.0
    out[..., 3, 3] = 1.0
    return out


def _cross(a: tuple[Tensor, Tensor, Tensor], b: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _exp_entries(v: tuple, w: tuple, s: Tensor, f: Tensor, g: Tensor) -> tuple[list[list[Tensor]], tuple]:
    """The 3 × 4 top entries of exp(ξ^) from the components of v, ω and the coefficients s, f, g:
    R = cos φ·I + s·ω^ + f·ωωᵀ (ω^² = ωωᵀ − φ²I, cos φ = 1 − f·φ²), p = s·v + f·ω×v + g·(ω·v)·ω
    (ω×(ω×v) = (ω·v)ω − φ²v and 1 − g·φ² = s). Also returns ω × v (the tangent reuses it)."""
    wx, wy, wz = w
    phi_sq = wx * wx + wy * wy + wz * wz
    c = 1 - f * phi_sq
    fx, fy, fz = f * wx, f * wy, f * wz
    sx, sy, sz = s * wx, s * wy, s * wz
    wv = _cross(w, v)
    gwv = g * (wx * v[0] + wy * v[1] + wz * v[2])
    p = [s * v[i] + f * wv[i] + gwv * w[i] for i in range(3)]
    rows = [[c + fx * wx, fx * wy - sz, fx * wz + sy, p[0]],
            [fy * wx + sz, c + fy * wy, fy * wz - sx, p[1]],
            [fz * wx - sy, fz * wy + sx, c + fz * wz, p[2]]]
    return rows, wv


def twist_exp(xi: Tensor) -> Tensor:
    """exp of se(3) twists: (..., 6) = (v [m], ω [rad]) → homogeneous transforms (..., 4, 4).

    The one closed form of the exponential in the package (module docstring); equals
    torch.linalg.matrix_exp of ξ^ (tested) at a fraction of its cost.
    """
    v, w = xi[..., :3].unbind(-1), xi[..., 3:].unbind(-1)
    s, f, g = exp_coefficients((xi[..., 3:] ** 2).sum(-1))
    return _pose_from_entries(_exp_entries(v, w, s, f, g)[0], s)


def twist_exp_and_tangents(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """exp of twists ξ = (v, ω) (..., 6) and its first derivative along T directions dξ (..., T, 6).

    Returns the pose T = exp(ξ^) (..., 4, 4) (:func:`twist_exp`) and, per direction, the spatial tangent of T:
    the angular velocity b = vee(dR·Rᵀ) (..., T, 3) [rad per unit] and the velocity of the frame's origin
    dp (..., T, 3) [m per unit], so that dT = [[b^·R, dp], [0, 0]]. With φ² = ‖ω‖²:
    b = J_l(ω)·dω = dω + f·ω×dω + g·ω×(ω×dω) (the left Jacobian of SO(3)), and dp the derivative of
    p = s·v + f·ω×v + g·(ω·v)·ω with ds = s'·dφ², …, dφ² = 2ω·dω (s', f', g': :func:`exp_coefficients_and_derivatives`).
    """
    vt, wt = xi[..., :3], xi[..., 3:]
    v, w = vt.unbind(-1), wt.unbind(-1)
    s, f, g, ds, df, dg = exp_coefficients_and_derivatives((wt * wt).sum(-1))
    rows, wv = _exp_entries(v, w, s, f, g)
    pose = _pose_from_entries(rows, s)
    at = lambda c: c.unsqueeze(-1)  # noqa: E731   (...) → (..., 1), broadcast over the T directions
    dv, dw = dxi[..., :3], dxi[..., 3:]
    w1, v1, wv1 = wt.unsqueeze(-2), vt.unsqueeze(-2), torch.stack(wv, -1).unsqueeze(-2)
    dphi_sq = 2 * (w1 * dw).sum(-1, keepdim=True)                                              # (..., T, 1)
    wdw = torch.linalg.cross(w1.expand_as(dw), dw)
    ang = dw + at(at(f)) * wdw + at(at(g)) * torch.linalg.cross(w1.expand_as(dw), wdw)
    w_dot_v = (wt * vt).sum(-1)[..., None, None]
    dw_dot_v = (dw * v1).sum(-1, keepdim=True) + (w1 * dv).sum(-1, keepdim=True)
    dwv = torch.linalg.cross(dw, v1.expand_as(dw)) + torch.linalg.cross(w1.expand_as(dv), dv)
    lin = (at(at(s)) * dv + at(at(ds)) * dphi_sq * v1 + at(at(f)) * dwv + at(at(df)) * dphi_sq * wv1
           + at(at(g)) * (dw_dot_v * w1 + w_dot_v * dw) + at(at(dg)) * dphi_sq * w_dot_v * w1)
    return pose, ang, lin


def twist_exp_and_tangent(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor]:
    """exp of twists ξ (..., 6) (:func:`twist_exp`, (..., 4, 4)) and its tangents as matrices (..., T, 4, 4)
    along dξ (..., T, 6): dT = [[b^·R, dp], [0, 0]] of :func:`twist_exp_and_tangents`."""
    pose, ang, lin = twist_exp_and_tangents(xi, dxi)
    drot = hat(ang) @ pose[..., None, :3, :3]
    return pose, pose_from_parts(drot, lin, lin.new_zeros(1, 4))


def roll_z_and_tangents(poses: Tensor, ang: Tensor, lin: Tensor, alpha: Tensor,
                        alpha_row: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rz(α)·T and its spatial tangents from those of T: poses (..., 4, 4), tangents ang, lin (..., T, 3)
    (:func:`twist_exp_and_tangents`), roll α (...) [rad], ``alpha_row`` (..., T, 1): 1 on the direction that
    is the roll angle itself, 0 elsewhere. Every vector is rotated by Rz(α); along α the roll adds its own
    velocity, b += e_z, dp += e_z × (Rz(α)·p)."""
    rolled = roll_z(poses, alpha)
    c, s = torch.cos(alpha)[..., None, None], torch.sin(alpha)[..., None, None]

    def rz(x: Tensor) -> Tensor:
        return torch.cat([c * x[..., :1] - s * x[..., 1:2], s * x[..., :1] + c * x[..., 1:2], x[..., 2:]], -1)

    p = rolled[..., None, :3, 3]
    zero = torch.zeros_like(p[..., :1])
    spin = torch.cat([-p[..., 1:2], p[..., :1], zero], -1)                                    # e_z × p
    unit_z = torch.cat([zero, zero, torch.ones_like(zero)], -1)
    return rolled, rz(ang) + alpha_row * unit_z, rz(lin) + alpha_row * spin


def chain_jacobian(poses: Tensor, ang: Tensor, lin: Tensor) -> tuple[Tensor, Tensor]:
    """The chain product rule: tip pose and base-frame Jacobian of a product of transforms.

    poses (..., n, 4, 4): T_1 … T_n, each relative to the end of the previous one; ang, lin (..., n, T, 3):
    spatial tangents of each T_k in its own base frame (b = vee(dT_k's dR·Rᵀ), dp: :func:`twist_exp_and_tangents`)
    along T directions each. Returns the tip pose T_1⋯T_n (..., 4, 4) and J (..., 6, n·T): per factor and
    direction, the velocity of the tip point (rows 0–2) and the angular velocity (rows 3–5), both in the base
    frame. With P_k = T_1⋯T_k, R_{k−1} the rotation of P_{k−1} and o_k the origin of P_k:
    ω = R_{k−1}·b, v = R_{k−1}·dp + ω × (p_tip − o_k).
    """
    ends = chain_products(poses)                                                          # (..., n, 4, 4)
    tip = ends[..., -1, :, :]
    eye = torch.eye(3, dtype=poses.dtype, device=poses.device).expand(*poses.shape[:-3], 1, 3, 3)
    bases = torch.cat([eye, ends[..., :-1, :3, :3]], dim=-3).unsqueeze(-3)                 # (..., n, 1, 3, 3)
    omega = (bases @ ang.unsqueeze(-1)).squeeze(-1)                                      # (..., n, T, 3)
    arm = (tip[..., None, :3, 3] - ends[..., :3, 3]).unsqueeze(-2)                         # (..., n, 1, 3)
    vel = (bases @ lin.unsqueeze(-1)).squeeze(-1) + torch.linalg.cross(omega, arm.expand_as(omega))
    return tip, torch.cat([vel, omega], dim=-1).flatten(-3, -2).mT


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
