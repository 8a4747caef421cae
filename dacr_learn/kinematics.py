"""Constant-curvature kinematics from Clarke features (docs/design.md §2).

A segment with bending vector u = (ρ_re, ρ_im)/d and length β is exp of the twist :func:`cc_twist` (rotation about
(−u_y, u_x, 0) by φ = ‖u‖), a twisting segment first rolled by α about its base z axis: T = Rz(α)·T_cc; through
the closed forms of :mod:`.lie`, finite with finite gradients at the straight configuration (no atan2, no ÷ φ).

Shapes: features (..., m, 4) with columns (ρ_re [m], ρ_im [m], β [m], α [rad]); poses are
homogeneous (..., 4, 4) [m]. Columns a segment does not actuate are ignored (β = l, α = 0).
"""
from __future__ import annotations

import functools

import torch
from torch import Tensor

from .checks import check_tensor
from .lie import chain_products, exp_coefficients_and_derivatives, exp_components, pose_of_components, roll_components
from .robot import RobotSpec


@functools.lru_cache(maxsize=64)
def _segment_values(spec: RobotSpec) -> tuple[tuple, tuple, tuple, tuple]:
    segs = spec.segments
    return (tuple(s.radius for s in segs), tuple(s.length for s in segs),
            tuple(s.extends for s in segs), tuple(s.twists for s in segs))


def _segment_constants(spec: RobotSpec, dtype: torch.dtype, device: torch.device):
    """(radius, length, extends, twists) per segment as tensors, (m,) each.

    Built on every call (only the Python values are cached): a tensor cache would keep the fake
    tensors created while torch.export / torch.compile trace a call and return them to later
    eager calls.
    """
    radius, length, extends, twists = _segment_values(spec)
    return (torch.tensor(radius, dtype=dtype, device=device), torch.tensor(length, dtype=dtype, device=device),
            torch.tensor(extends, device=device), torch.tensor(twists, device=device))


def _segment_parameters(spec: RobotSpec, features: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
    """Bending vector u = ρ/d (..., m, 2), length β (..., m) with β = l where not actuated, and
    roll α (..., m) with α = 0 where not actuated, or None if no segment twists."""
    check_tensor(features, "features", (spec.num_segments, 4))
    radius, length, extends, twists = _segment_constants(spec, features.dtype, features.device)
    u = features[..., :2] / radius.unsqueeze(-1)
    beta = torch.where(extends, features[..., 2], length)
    alpha = torch.where(twists, features[..., 3], 0.0) if any(s.twists for s in spec.segments) else None
    return u, beta, alpha


def effective_features(spec: RobotSpec, features: Tensor) -> Tensor:
    """Replace non-actuated columns by their fixed values (β = l, α = 0). (..., m, 4) → (..., m, 4)."""
    _, beta, alpha = _segment_parameters(spec, features)
    alpha = torch.zeros_like(beta) if alpha is None else alpha
    return torch.cat([features[..., :2], beta.unsqueeze(-1), alpha.unsqueeze(-1)], dim=-1)


def cc_twist(u: Tensor, beta: Tensor) -> Tensor:
    """The twist ξ = (v, ω) (..., 6) of a constant-curvature segment: v = (0, 0, β), ω = (−u_y, u_x, 0), for the
    bending vector u (..., 2) [rad] and length β (...) [m]; exp(ξ^) is the segment's pose (docs/design.md §2).
    Linear in (u, β): a change du, dβ is the twist (0, 0, dβ, −du_y, du_x, 0)."""
    zero = torch.zeros_like(u[..., 0]).expand(torch.broadcast_shapes(u.shape[:-1], beta.shape))
    return torch.stack([zero, zero, beta.expand_as(zero), -u[..., 1].expand_as(zero), u[..., 0].expand_as(zero),
                        zero], dim=-1)


def cc_transform(u: Tensor, beta: Tensor, alpha: Tensor | None = None) -> Tensor:
    """Rz(α)·exp(ξ_cc^) for bending vector u (..., 2) [rad], length β (...) [m], roll α (...) [rad] → (..., 4, 4).

    ``alpha=None`` means no roll. The kernel's exponential (:func:`~.lie.exp_components`) of :func:`cc_twist`,
    its zero components skipped: R = I + s·K + f·K², p = β·(f·u_x, f·u_y, s).
    """
    rot, pos = exp_components((None, None, beta), (-u[..., 1], u[..., 0], None))
    return pose_of_components(*(rot, pos) if alpha is None else roll_components(alpha, rot, pos))


def _rz(ca: Tensor, sa: Tensor, v: Tensor) -> Tensor:
    """Rz(α)·v for stacked vectors v (3, ..., m, M) and cos α, sin α (m, M)."""
    return torch.stack([ca * v[0] - sa * v[1], sa * v[0] + ca * v[1], v[2]])


def _rotate(rot: Tensor, v: Tensor) -> Tensor:
    """rot·v for rotations rot (3, 3, m, M) and stacked vectors v (3, T, m, M) (T directions): nine fused
    multiply-adds on contiguous (T, m, M) blocks, no (3, 3, T, m, M) temporary."""
    return torch.stack([torch.addcmul(torch.addcmul(rot[i, 0] * v[0], rot[i, 1], v[1]), rot[i, 2], v[2])
                        for i in range(3)])


def cc_pose_and_jacobian(spec: RobotSpec, features: Tensor,
                         columns: list[tuple[int, int]] | None = None) -> tuple[Tensor, Tensor]:
    """Tip pose and its Jacobian w.r.t. feature columns, in closed form: features (..., m, 4) → pose (..., 4, 4) [m]
    and J: the tip point's velocity [m] and angular velocity [rad] in the base frame per unit of each column.
    ``columns``: None for every (ρ_re, ρ_im, β, α) of every segment, J (..., 6, m, 4), columns a segment does not
    actuate zero; or a list of (segment, column index 0–3) pairs, J (..., 6, len(columns)) (e.g. the actuated
    features).

    One batched evaluation for all segments of all samples (the op count does not grow with the batch and hardly with
    m), in a batch-last layout: every quantity is a stack of contiguous (m, M) blocks, M the flattened batch. Per
    segment, u = ρ/d, φ² = ‖u‖², s, f, g, s', f' (:func:`~.lie.exp_coefficients_and_derivatives`): the pose
    R = cos φ·I + s·ω^ + f·ωωᵀ, p = β·(f·u_x, f·u_y, s) of the twist ξ = (0, 0, β; ω = (−u_y, u_x, 0)), and its spatial
    tangents along (u_x, u_y, β): angular b = J_l(ω)·dω = dω + f·ω×dω + g·ω×(ω×dω), i.e. b_x = (−g·u_x·u_y, 1 − g·u_y²,
    −f·u_y), b_y = (g·u_x² − 1, g·u_x·u_y, f·u_x), b_β = 0, and linear dp_x = β·(f + 2f'·u_x², 2f'·u_x·u_y, 2s'·u_x),
    dp_y = β·(2f'·u_x·u_y, f + 2f'·u_y², 2s'·u_y), dp_β = (f·u_x, f·u_y, s); a twisting segment is rolled, Rz(α)·T, its
    tangents rotated and the roll's own (b, dp) = (e_z, e_z × p) added. The chain rule of :func:`~.lie.chain_components`
    transports all directions of all segments at once. ∂/∂ρ = ∂/∂u / d.

    The returned J and pose are views whose batch is innermost in memory (rows-last: ``J.permute(-2, -1, …)`` of a
    contiguous (6, D, M) block); ``.contiguous()`` gives the row-major copy.
    """
    check_tensor(features, "features", (spec.num_segments, 4))
    m, lead, dtype, device = spec.num_segments, features.shape[:-2], features.dtype, features.device
    radius, length, extends, twists = _segment_constants(spec, dtype, device)
    segs = spec.segments
    f = features.reshape(-1, m, 4).permute(2, 1, 0).contiguous()                      # (4, m, M)
    u = f[:2] * (1 / radius).unsqueeze(-1)                                             # (2, m, M)
    ux, uy = u[0], u[1]
    beta = f[2] if all(s.extends for s in segs) else torch.where(extends.unsqueeze(-1), f[2], length.unsqueeze(-1))
    y = torch.addcmul(ux * ux, uy, uy)
    s, fc, g, ds, df = exp_coefficients_and_derivatives(y, 5)
    fu, su, gu = fc * u, s * u, g * u
    c = 1 - fc * y
    fxy, gxy = fu[0] * uy, gu[0] * uy
    rot = torch.stack([c + fu[1] * uy, -fxy, su[0], -fxy, c + fu[0] * ux, su[1], -su[0], -su[1], c]).unflatten(
        0, (3, 3))                                                                     # (3, 3, m, M)
    dir_p = torch.stack([fu[0], fu[1], s])                                             # dp_β = p / β
    pos = beta * dir_p
    q, sb = (2 * beta) * df, (2 * beta) * ds
    qx, fb = q * ux, fc * beta
    qxy = qx * uy
    wanted = [(k, c_) for k in range(m) for c_ in range(4)] if columns is None else list(columns)
    used = [c_ for c_ in range(4) if any(cc == c_ for _, cc in wanted)
            and (c_ != 3 or any(s_.twists for s_ in segs)) and (c_ != 2 or any(s_.extends for s_ in segs))]
    zero = torch.zeros_like(y)
    per_dir = {0: ((-gxy, 1 - gu[1] * uy, -fu[1]), (torch.addcmul(fb, qx, ux), qxy, sb * ux)),
               1: ((gu[0] * ux - 1, gxy, fu[0]), (qxy, torch.addcmul(fb, q * uy, uy), sb * uy))}
    lin_dirs = [c_ for c_ in used if c_ != 3] or [0]                                  # directions in J's order
    order = lin_dirs + [c_ for c_ in used if c_ == 3]
    t = len(lin_dirs)
    local = torch.stack([per_dir[c_][j][i] if c_ < 2 else zero if j == 0 else dir_p[i]              # (3, 2T, m, M):
                         for i in range(3) for j in range(2) for c_ in lin_dirs]).unflatten(0, (3, 2 * t))  # b's, dp's
    scale = torch.stack([(1 / radius) if c_ < 2 else extends.to(dtype) for c_ in lin_dirs] * 2).unsqueeze(-1)
    local = local * scale                                                              # per unit ρ, β
    if any(s_.twists for s_ in segs):
        alpha = torch.where(twists.unsqueeze(-1), f[3], 0.0)
        ca, sa = alpha.cos(), alpha.sin()
        rot, pos, local = _rz(ca, sa, rot), _rz(ca, sa, pos), _rz(ca, sa, local)
        if 3 in used:
            roll = twists.to(dtype).unsqueeze(-1)
            local = torch.cat([local[:, :t], torch.stack([zero, zero, roll.expand_as(zero)]).unsqueeze(1), local[:, t:],
                               torch.stack([-roll * pos[1], roll * pos[0], zero]).unsqueeze(1)], 1)
            t += 1
    tip_rot, tip_pos = rot[:, :, 0], pos[:, 0]                                         # the chain T_1⋯T_k
    bases, origins = [], [tip_pos]
    for k in range(1, m):
        bases.append(tip_rot)
        tip_pos = tip_pos + (tip_rot * pos[:, k].unsqueeze(0)).sum(1)
        tip_rot = (tip_rot.unsqueeze(2) * rot[:, :, k].unsqueeze(0)).sum(1)
        origins.append(tip_pos)
    if m > 1:
        local = torch.cat([local[:, :, :1], _rotate(torch.stack(bases, 2), local[:, :, 1:])], 2)
    omega, vel = local[:, :t], local[:, t:]
    arm = (tip_pos.unsqueeze(1) - torch.stack(origins, 1)).unsqueeze(1)              # (3, 1, m, M)
    vel = vel + torch.stack([torch.addcmul(omega[1] * arm[2], omega[2], arm[1], value=-1),
                             torch.addcmul(omega[2] * arm[0], omega[0], arm[2], value=-1),
                             torch.addcmul(omega[0] * arm[1], omega[1], arm[0], value=-1)])
    jac = torch.cat([vel, omega]).flatten(1, 2)                                        # (6, T·m, M), index d·m + k
    index = [order.index(c_) * m + k if c_ in used else t * m for k, c_ in wanted]
    if t * m in index:                                                                 # a column no segment has
        jac = torch.cat([jac, torch.zeros_like(jac[:, :1])], 1)
    jac = jac.index_select(1, torch.tensor(index, device=device))                      # (6, D, M)
    jac = jac.permute(2, 0, 1).reshape(*lead, 6, len(wanted))
    if columns is None:
        jac = jac.unflatten(-1, (m, 4))
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device).view(1, 4, 1).expand(1, 4, y.shape[-1])
    pose = torch.cat([torch.cat([tip_rot, tip_pos.unsqueeze(1)], 1), bottom]).permute(2, 0, 1)
    return pose.reshape(*lead, 4, 4), jac


def segment_poses(spec: RobotSpec, features: Tensor) -> Tensor:
    """Pose of each segment's tip relative to its own base: (..., m, 4) → (..., m, 4, 4)."""
    return cc_transform(*_segment_parameters(spec, features))


def segment_tip_poses(spec: RobotSpec, features: Tensor) -> Tensor:
    """Pose of each segment's tip in the robot base frame: (..., m, 4) → (..., m, 4, 4)."""
    return chain_products(segment_poses(spec, features))


def forward_kinematics(spec: RobotSpec, features: Tensor) -> Tensor:
    """Tip pose T⁽¹⁾T⁽²⁾…T⁽ᵐ⁾ in the base frame: features (..., m, 4) → (..., 4, 4) [m]."""
    return chain_products(segment_poses(spec, features), tip_only=True)


def backbone_points(spec: RobotSpec, features: Tensor, points_per_segment: int = 16) -> Tensor:
    """Backbone points for drawing: (..., m, 4) → (..., 1 + m·points_per_segment, 3) [m].

    The first point is the base origin; then, per segment, the arc at s = β·k/K, k = 1..K.
    """
    if points_per_segment < 1:
        raise ValueError(f"points_per_segment: expected >= 1, got {points_per_segment}")
    u, beta, alpha = _segment_parameters(spec, features)
    frac = torch.arange(1, points_per_segment + 1, dtype=u.dtype, device=u.device) / points_per_segment
    u_partial = u.unsqueeze(-3) * frac[:, None, None]                              # (..., K, m, 2)
    beta_partial = beta.unsqueeze(-2) * frac[:, None]                              # (..., K, m)
    rot, pos = exp_components((None, None, beta_partial), (-u_partial[..., 1], u_partial[..., 0], None))
    if alpha is not None:                                                          # positions only: no 4×4 poses
        rot, pos = roll_components(alpha.unsqueeze(-2), rot, pos)
    zero = torch.zeros_like(beta_partial)
    partial = torch.stack([zero if c is None else c.expand_as(zero) for c in pos], dim=-1)   # (..., K, m, 3)
    bases = chain_products(cc_transform(u, beta, alpha))                                   # (..., m, 4, 4)
    eye = torch.eye(4, dtype=u.dtype, device=u.device).expand(*bases.shape[:-3], 1, 4, 4)
    bases = torch.cat([eye, bases[..., :-1, :, :]], dim=-3).unsqueeze(-4)          # base of each segment
    world = (bases[..., :3, :3] @ partial.unsqueeze(-1)).squeeze(-1) + bases[..., :3, 3]   # (..., K, m, 3)
    pts = world.transpose(-2, -3).flatten(-3, -2)                                  # (..., m·K, 3)
    origin = torch.zeros_like(pts[..., :1, :])
    return torch.cat([origin, pts], dim=-2)


def analytic_inverse_kinematics(spec: RobotSpec, position: Tensor) -> Tensor:
    """Closed-form IK of one type-0 or type-I segment: tip position (..., 3) [m] → features (..., 1, 4).

    θ = atan2(y, x), φ = 2·atan2(r, z), ρ = d·φ·(cos θ, sin θ) = d·(φ/r)·(x, y); for type I
    β = ‖p‖·φ / (2 sin(φ/2)); for type 0 β = l (the position must be reachable). Finite at r = 0.
    """
    if spec.num_segments != 1 or spec.segments[0].type not in ("0", "I"):
        raise ValueError(f"spec: analytic IK needs one segment of type 0 or I, got "
                         f"{[s.type for s in spec.segments]}")
    check_tensor(position, "position", (3,))
    seg = spec.segments[0]
    x, y, z = position.unbind(-1)
    r_sq = x * x + y * y
    small = r_sq < 1e-12 * seg.length**2
    r = torch.sqrt(torch.where(small, torch.ones_like(r_sq), r_sq))
    ratio_big = 2 * torch.atan2(r, z) / r
    z_safe = torch.where(small, z, torch.ones_like(z))
    ratio_small = 2 / z_safe * (1 - r_sq / (3 * z_safe**2))                     # 2 atan(r/z)/r, z > 0
    phi_over_r = torch.where(small, ratio_small, ratio_big)
    phi = phi_over_r * torch.sqrt(r_sq + torch.finfo(position.dtype).tiny)
    if seg.extends:
        norm = torch.linalg.vector_norm(position, dim=-1)
        beta = norm / torch.sinc(phi / (2 * torch.pi))                           # ‖p‖·φ/(2 sin(φ/2))
    else:
        beta = torch.full_like(x, seg.length)
    feat = torch.stack([seg.radius * phi_over_r * x, seg.radius * phi_over_r * y, beta, torch.zeros_like(x)], -1)
    return feat.unsqueeze(-2)
