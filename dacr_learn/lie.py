"""SE(3) / se(3) in closed form, batched and differentiable: the one place the twist maths lives.

A twist ξ = (v, ω) (..., 6) [m, rad] has the matrix ξ^ = [[ω^, v], [0, 0]] and the exponential

    exp(ξ^) = [[R, p], [0, 1]],  R = I + s·ω^ + f·ω^²,  p = (I + f·ω^ + g·ω^²)·v,
    s = sin φ/φ,  f = (1 − cos φ)/φ²,  g = (φ − sin φ)/φ³,  φ = ‖ω‖,

with s, f, g written as functions of φ² that are finite, with finite derivatives, at φ = 0 (Taylor
polynomials below :data:`TAYLOR_BELOW`). A constant-curvature segment is the exponential of a twist that
is linear in its Clarke coordinates (docs/design.md §2), so the CC kinematics (:mod:`.kinematics`), the
compositional FK (:mod:`.compositional`), the IK solver and every folded inference module
(:mod:`.deploy`, :mod:`.hardware.deploy`) build on these functions: one closed form of the exponential
(:func:`exp_components`), its tangent (:func:`exp_components_and_tangents`) and one chain product rule
(:func:`chain_components`). Pure torch, any leading batch dims.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .component_algebra import Rot3, Vec3, add, components, cross, dense, dot, matmul, matvec, neg, prod, scaled

__all__ = [
    "TAYLOR_BELOW", "bending_coefficients", "bending_coefficients_and_derivatives", "chain_products", "hat",
    "pose_from_parts", "third_coefficient", "twist_chain_jacobian", "twist_exp", "twist_jacobian", "roll_z", "vee",
]

TAYLOR_BELOW = 1e-2   # φ² below which s, f, g and their derivatives are Taylor polynomials (exact to ~1e-14)

# Taylor coefficients in y = φ² (degree 0 … 4) of s = sin φ/φ, f = (1 − cos φ)/φ², g = (1 − s)/φ² = (φ − sin φ)/φ³
# and their y-derivatives s', f', g', one per row (:func:`exp_coefficients_and_derivatives`).
_SERIES = ((1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880),
           (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),
           (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),
           (-1 / 6, 2 / 120, -3 / 5040, 4 / 362880, -5 / 39916800),
           (-1 / 24, 2 / 720, -3 / 40320, 4 / 3628800, -5 / 479001600),
           (-1 / 120, 2 / 5040, -3 / 362880, 4 / 39916800, -5 / 6227020800))


def exp_coefficients_and_derivatives(phi_sq: Tensor, count: int = 6) -> Tensor:
    """The first ``count`` of (s, f, g, ds, df, dg) of φ² (...), stacked (count, ...): the coefficients of exp of a
    twist (:func:`twist_exp`) and their φ²-derivatives, finite with finite derivatives at 0. Below
    :data:`TAYLOR_BELOW` the Taylor polynomials (:data:`_SERIES`) in one Horner pass; above it the closed forms,
    f as 2·(sin(φ/2)/φ)² (no cancellation, accurate in float32 too), ds = (cos φ − s)/(2φ²), df = (s − 2f)/(2φ²),
    g = (1 − s)/φ², dg = −(ds + g)/φ²."""
    small = phi_sq < TAYLOR_BELOW
    y = phi_sq.clamp(max=TAYLOR_BELOW)                     # no large powers where the closed forms are taken
    series = torch.tensor(_SERIES[:count], dtype=y.dtype, device=y.device).T.reshape(5, count, *[1] * y.dim())
    taylor = torch.addcmul(series[3], series[4], y)
    for j in (2, 1, 0):
        taylor = torch.addcmul(series[j], taylor, y)
    y_big = torch.where(small, 1.0, phi_sq)
    phi = y_big.sqrt()
    inv_phi = phi.reciprocal()
    s = phi.sin() * inv_phi
    half = (0.5 * phi).sin() * inv_phi
    big = [s, 2 * half * half, (1 - s) / y_big]
    if count > 3:
        half_inv_y = 0.5 / y_big
        big += [(phi.cos() - s) * half_inv_y, (s - 2 * big[1]) * half_inv_y]
    if count > 5:
        big.append(-(big[3] + big[2]) / y_big)
    return torch.where(small, taylor, torch.stack(big[:count]))


def bending_coefficients(phi_sq: Tensor) -> tuple[Tensor, Tensor]:
    """s = sin φ/φ and f = (1 − cos φ)/φ² as functions of φ² (..., ), finite with finite gradients at 0.

    f is evaluated as 2·(sin(φ/2)/φ)², which has no cancellation (accurate in float32 too).
    """
    s, f = exp_coefficients_and_derivatives(phi_sq, 2)
    return s, f


def bending_coefficients_and_derivatives(phi_sq: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """s, f (:func:`bending_coefficients`) and their derivatives ds/dφ², df/dφ² (..., ) (Taylor branch
    near 0, below the same threshold)."""
    s, f, _, ds, df = exp_coefficients_and_derivatives(phi_sq, 5)
    return s, f, ds, df


def third_coefficient(phi_sq: Tensor, s: Tensor) -> Tensor:
    """g = (φ − sin φ)/φ³ = (1 − s)/φ² as a function of φ² (..., ), finite with finite gradients at 0; ``s`` =
    sin φ/φ of the same φ² (:func:`bending_coefficients`) is not needed, g comes from φ² alone."""
    return exp_coefficients_and_derivatives(phi_sq, 3)[2]


def hat(w: Tensor) -> Tensor:
    """Skew matrices ω^ (..., 3, 3) of vectors ω (..., 3): ω^·x = ω × x."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack([zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0],
                        -w[..., 1], w[..., 0], zero], dim=-1).unflatten(-1, (3, 3))


def vee(w_hat: Tensor) -> Tensor:
    """ω (..., 3) of skew matrices ω^ (..., 3, 3) (the inverse of :func:`hat`; the skew part is read)."""
    return 0.5 * torch.stack([w_hat[..., 2, 1] - w_hat[..., 1, 2], w_hat[..., 0, 2] - w_hat[..., 2, 0],
                              w_hat[..., 1, 0] - w_hat[..., 0, 1]], dim=-1)


def twist_jacobian(pose: Tensor, dpose: Tensor) -> Tensor:
    """Tip-twist Jacobian from a pose (..., 4, 4) and its derivative (..., 4, 4, k) → (..., 6, k): rows dp (the
    tip point's linear velocity) and ω = vee(dR·Rᵀ), both in the base frame."""
    omega = vee(dpose[..., :3, :3, :].movedim(-1, -3) @ pose[..., None, :3, :3].mT)        # (..., k, 3)
    return torch.cat([dpose[..., :3, 3, :], omega.mT], dim=-2)


def pose_from_parts(rotation: Tensor, position: Tensor, bottom: Tensor | None = None) -> Tensor:
    """Homogeneous pose (..., 4, 4) from rotation (..., 3, 3) and position (..., 3).

    ``bottom``: the row (0, 0, 0, 1) as a (1, 4) tensor of the right dtype/device, if the caller
    keeps one (the exported inference modules hold it as a buffer); built here otherwise.
    """
    top = torch.cat([rotation, position.unsqueeze(-1)], dim=-1)
    bottom = top.new_tensor([0.0, 0.0, 0.0, 1.0]) if bottom is None else bottom     # as pose_of_components'
    return torch.cat([top, bottom.expand(*top.shape[:-2], 1, 4)], dim=-2)


# Component form: vectors as 3 tensors, rotations as 9 (row-major), any common shape (...). Elementwise
# torch ops on contiguous tensors of one shape are several times faster on CPU than ops that broadcast a
# (..., 3) or (..., T, 3) layout, so the kernel computes in this form; the (..., 6) / (..., 4, 4) functions
# below convert at the boundary. Tangent components carry T directions in front, (T, ...): per-sample
# coefficients (...) broadcast over the leading dim, which keeps the inner loop contiguous. The arithmetic on
# components (None = an exact zero) is :mod:`.component_algebra`.


def exp_components(v: Vec3, w: Vec3) -> tuple[Rot3, Vec3]:
    """exp(ξ^) of ξ = (v, ω) in component form (rotation R as 9 entries, position p as 3):
    R = cos φ·I + s·ω^ + f·ωωᵀ (ω^² = ωωᵀ − φ²I, cos φ = 1 − f·φ²), p = s·v + f·ω×v + g·(ω·v)·ω
    (ω×(ω×v) = (ω·v)ω − φ²v and 1 − g·φ² = s). The g term costs nothing where ω·v is an exact zero (None
    components, e.g. a CC twist's)."""
    s, f, g = exp_coefficients_and_derivatives(_phi_sq(v, w), 3)
    return _exp_from_coefficients(v, w, s, f, g)


def _phi_sq(v: Vec3, w: Vec3) -> Tensor:
    phi_sq = dot(w, w)
    return torch.zeros_like(next(c for c in v if c is not None)) if phi_sq is None else phi_sq


def _exp_from_coefficients(v: Vec3, w: Vec3, s: Tensor, f: Tensor, g: Tensor) -> tuple[Rot3, Vec3]:
    c = 1 - f * _phi_sq(v, w)
    fw, sw = scaled(f, w), scaled(s, w)
    rot = (add(c, prod(fw[0], w[0])), add(prod(fw[0], w[1]), neg(sw[2])), add(prod(fw[0], w[2]), sw[1]),
           add(prod(fw[1], w[0]), sw[2]), add(c, prod(fw[1], w[1])), add(prod(fw[1], w[2]), neg(sw[0])),
           add(prod(fw[2], w[0]), neg(sw[1])), add(prod(fw[2], w[1]), sw[0]), add(c, prod(fw[2], w[2])))
    wv, gwv = cross(w, v), prod(g, dot(w, v))
    return rot, tuple(add(prod(s, v[i]), prod(f, wv[i]), prod(gwv, w[i])) for i in range(3))


def exp_components_and_tangents(v: Vec3, w: Vec3, directions: list[tuple[Vec3, Vec3]]) -> tuple:
    """:func:`exp_components` and its spatial tangents along each of the ``directions`` (dv, dw).

    Per direction: the angular velocity b = vee(dR·Rᵀ) = J_l(ω)·dω = dω + f·ω×dω + g·ω×(ω×dω) (the left
    Jacobian of SO(3)) and the velocity of the origin dp, the derivative of p = s·v + f·ω×v + g·(ω·v)·ω with
    ds = s'·dφ², …, dφ² = 2ω·dω (s', f', g': :func:`exp_coefficients_and_derivatives`). A direction's
    components broadcast against the twist's: shape (...) or (T, ...) for T directions at once. Returns
    (R, p, [(b, dp) per direction]); components that are exactly zero may be None (no operation is spent on
    them: a sparse direction such as one Clarke coordinate of a CC segment costs a few operations).
    """
    s, f, g, ds, df, dg = exp_coefficients_and_derivatives(_phi_sq(v, w))
    rot, pos = _exp_from_coefficients(v, w, s, f, g)
    wv, w_v = cross(w, v), dot(w, v)
    gw_v = prod(g, w_v)
    tangents = []
    for dv, dw in directions:
        dphi = prod(2, dot(w, dw))
        wdw = cross(w, dw)
        ang = tuple(add(dw[i], prod(f, wdw[i]), prod(g, c)) for i, c in enumerate(cross(w, wdw)))
        dwv = tuple(add(a, b) for a, b in zip(cross(dw, v), cross(w, dv), strict=True))
        dsp, dfp = prod(ds, dphi), prod(df, dphi)
        dg_w_v = add(prod(dg, dphi, w_v), prod(g, add(dot(dw, v), dot(w, dv))))
        lin = tuple(add(prod(s, dv[i]), prod(dsp, v[i]), prod(f, dwv[i]), prod(dfp, wv[i]), prod(dg_w_v, w[i]),
                         prod(gw_v, dw[i])) for i in range(3))
        tangents.append((ang, lin))
    return rot, pos, tangents


def roll_components(alpha: Tensor, rot: Rot3, pos: Vec3, tangents: list[tuple[Vec3, Vec3]] | None = None,
                    roll_direction: tuple[int, Tensor | float] | None = None) -> tuple:
    """Rz(α)·T in component form: (R, p) → (Rz·R, Rz·p); with ``tangents`` [(b, dp), …] also the rolled tangents
    Rz·b, Rz·dp, and on the direction that is α itself (``roll_direction`` = (its index, a weight: 1, or a
    per-sample 0/1 where only some samples roll)) the roll's own velocity: b += e_z, dp += e_z × (Rz·p).
    Returns (R', p'[, tangents'])."""
    c, s = torch.cos(alpha), torch.sin(alpha)

    def rz(x: tuple) -> tuple:
        return (add(prod(c, x[0]), neg(prod(s, x[1]))), add(prod(s, x[0]), prod(c, x[1])), *x[2:])

    cols = rz(rot[0::3]), rz(rot[1::3]), rz(rot[2::3])
    rot = tuple(cols[j][i] for i in range(3) for j in range(3))                      # back to row-major
    pos = rz(pos)
    if tangents is None:
        return rot, pos
    rolled = [(rz(ang), rz(lin)) for ang, lin in tangents]
    if roll_direction is not None:
        t, weight = roll_direction
        ang, lin = rolled[t]
        ang = (ang[0], ang[1], add(ang[2], weight))
        lin = (add(lin[0], neg(prod(weight, pos[1]))), add(lin[1], prod(weight, pos[0])), lin[2])
        rolled[t] = (ang, lin)
    return rot, pos, rolled


def chain_components(rots: list[Rot3], poss: list[Vec3],
                     tangents: list[list[tuple[Vec3, Vec3]]] | None = None) -> tuple[Rot3, Vec3, list]:
    """The chain product rule in component form: factors T_1 … T_n (lists of R, p), each relative to the end
    of the previous one, with spatial tangents [(b, dp), …] of each factor in its own base frame. Returns the
    tip (R, p) and, per factor and direction, (v, ω): the velocity of the tip point and the angular velocity
    in the base frame. With P_k = T_1⋯T_k, R_{k−1} the rotation of P_{k−1} and o_k the origin of P_k:
    ω = R_{k−1}·b, v = R_{k−1}·dp + ω × (p_tip − o_k)."""
    bases, origins = [], []
    rot, pos = rots[0], poss[0]
    origins.append(pos)
    for r, p in zip(rots[1:], poss[1:], strict=True):
        bases.append(rot)
        pos = tuple(add(a, b) for a, b in zip(matvec(rot, p), pos, strict=True))
        rot = matmul(rot, r)
        origins.append(pos)
    columns = []
    for k, factor in enumerate(tangents or []):
        arm = tuple(add(t, neg(o)) for t, o in zip(pos, origins[k], strict=True))
        cols = []
        for b, dp in factor:
            omega, vel = (b, dp) if k == 0 else (matvec(bases[k - 1], b), matvec(bases[k - 1], dp))
            cols.append((tuple(add(a, c) for a, c in zip(vel, cross(omega, arm), strict=True)), omega))
        columns.append(cols)
    return rot, pos, columns


def pose_of_components(rot: Rot3, pos: Vec3) -> Tensor:
    """(..., 4, 4) homogeneous poses from component form (one stack and one cat)."""
    given = [c for c in (*rot, *pos) if c is not None]
    shape = torch.broadcast_shapes(*(c.shape for c in given))
    zero = torch.zeros_like(given[0]).expand(shape) if len(given) < 12 else None
    full = [zero if c is None else c if c.shape == shape else c.expand(shape)
            for c in (*rot[0:3], pos[0], *rot[3:6], pos[1], *rot[6:9], pos[2])]
    top = torch.stack(full, dim=-1).unflatten(-1, (3, 4))
    bottom = top.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*shape, 1, 4)
    return torch.cat([top, bottom], dim=-2)


def _rot_pos(poses: Tensor) -> tuple[Rot3, Vec3]:
    """Component form of poses (..., 4, 4)."""
    c = components(poses[..., :3, :].flatten(-2))
    return (*c[0:3], *c[4:7], *c[8:11]), (c[3], c[7], c[11])


def _directions(d: Tensor) -> tuple[Tensor, ...]:
    """(..., T, k) → k components (T, ...) (contiguous)."""
    return d.movedim(-1, 0).movedim(-1, 1).contiguous().unbind(0)


def twist_exp(xi: Tensor, alpha: Tensor | None = None) -> Tensor:
    """exp of se(3) twists: (..., 6) = (v [m], ω [rad]) → homogeneous transforms (..., 4, 4); with rolls α (...)
    [rad], Rz(α)·exp(ξ^) (:func:`roll_z`, in the same component pass).

    The one closed form of the exponential in the package (:func:`exp_components`); equals
    torch.linalg.matrix_exp of ξ^ (tested) at a fraction of its cost.
    """
    c = components(xi)
    rot, pos = exp_components(c[:3], c[3:])
    return pose_of_components(*(rot, pos) if alpha is None else roll_components(alpha, rot, pos))


def twist_chain_jacobian(xi: Tensor | tuple, dxi: Tensor | tuple, alpha: Tensor | None = None,
                         alpha_row: Tensor | None = None, base: Tensor | None = None,
                         point: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Tip pose and Jacobian of a product of exponentials, in component form from the twists to J (one layout
    conversion in, one out): the exponentials with their tangents (:func:`exp_components_and_tangents`), the
    rolls (:func:`roll_components`) and the chain product rule (:func:`chain_components`) in one call.

    xi (..., n, 6) twists of the factors E_k = [Rz(α_k)·]exp(ξ_k^); dxi (..., n, T, 6) (broadcast) their tangents
    along T directions each; or both as 6 components, xi's (..., n) and dxi's (T, ..., n) (broadcast), where
    None is an exact zero that costs no operation (e.g. a CC twist's, :func:`~.kinematics.cc_transform`);
    ``alpha`` (..., n) [rad] rolls with ``alpha_row`` (..., n, T, 1), 1 on the direction that is α_k itself;
    ``base`` (..., 4, 4): a fixed pose in front of E_1 (J is then in its base frame); ``point`` (..., 3) [m]: a
    point fixed in the frame of E_n (the tip is then that point). Returns the tip pose B·E_1⋯E_n·Trans(point)
    (..., 4, 4) and J (..., 6, n·T): per factor and direction, the velocity of the tip point (rows 0–2) and
    the angular velocity (rows 3–5), both in the base frame.
    """
    c = components(xi) if isinstance(xi, Tensor) else xi
    d = _directions(dxi.expand(*xi.shape[:-1], *dxi.shape[-2:])) if isinstance(dxi, Tensor) else dxi
    rot, pos, [(b, dp)] = exp_components_and_tangents(c[:3], c[3:], [(d[:3], d[3:])])
    if alpha is not None:
        rows = alpha_row.expand(*xi.shape[:-1], *alpha_row.shape[-2:])[..., 0].movedim(-1, 0)
        rot, pos, [(b, dp)] = roll_components(alpha, rot, pos, [(b, dp)], (0, rows))
    return _chain(rot, pos, b, dp, base, point)


def _chain(rot: Rot3, pos: Vec3, b: tuple, dp: tuple, base: Tensor | None, point: Tensor | None):
    """:func:`chain_components` of factors in component form (..., n) with tangents (T, ..., n), fixed ends."""
    n = next(x for x in pos if x is not None).shape[-1]
    at = lambda c, k: tuple(None if x is None else x[..., k] for x in c)  # noqa: E731
    rots, poss = [at(rot, k) for k in range(n)], [at(pos, k) for k in range(n)]
    tangents = [[(at(b, k), at(dp, k))] for k in range(n)]
    if base is not None:
        base_rot, base_pos = _rot_pos(base)
        rots, poss, tangents = [base_rot, *rots], [base_pos, *poss], [[], *tangents]
    if point is not None:
        rots.append((1.0, None, None, None, 1.0, None, None, None, 1.0))
        poss.append(components(point))
        tangents.append([])
    tip_rot, tip_pos, cols = chain_components(rots, poss, tangents)
    entries = [x for c in cols for (v, w) in c for x in (*v, *w)]                  # (factor, row), (T, ...)
    given = [x for x in entries if x is not None]
    entries = dense(entries, given[0].expand(torch.broadcast_shapes(*(x.shape for x in given))))
    jac = torch.stack(entries, dim=-1).movedim(0, -1).unflatten(-2, (n, 6)).transpose(-3, -2)   # (..., 6, n, T)
    return pose_of_components(tip_rot, tip_pos), jac.flatten(-2)


def chain_products(poses: Tensor, tip_only: bool = False) -> Tensor:
    """Products of transforms T⁽¹⁾ … T⁽ᵐ⁾, each relative to the end of the previous one (..., m, 4, 4): the running
    products T⁽¹⁾, T⁽¹⁾T⁽²⁾, … (..., m, 4, 4), or with ``tip_only`` the whole product T⁽¹⁾⋯T⁽ᵐ⁾ (..., 4, 4) alone
    (unrolled over m: no stack in an exported module)."""
    out = [poses[..., 0, :, :]]
    for j in range(1, poses.shape[-3]):
        out.append(out[-1] @ poses[..., j, :, :])
    return out[-1] if tip_only else torch.stack(out, dim=-3)


def roll_z(poses: Tensor, alpha: Tensor) -> Tensor:
    """Rz(α)·T: poses (..., 4, 4) rolled by α (...) [rad] about the z axis of the frame they are expressed in
    (:func:`roll_components`; α = 0 returns the poses' values unchanged)."""
    return pose_of_components(*roll_components(alpha, *_rot_pos(poses)))
