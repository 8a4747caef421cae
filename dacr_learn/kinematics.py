"""Constant-curvature kinematics from Clarke features (docs/design.md §2).

Per segment, with u = (ρ_re, ρ_im)/d, φ² = ‖u‖², s = sin φ/φ, f = (1 − cos φ)/φ²:
R = I + s·K + f·K² (rotation about (−u_y, u_x, 0) by φ), p = β·(u_x f, u_y f, s),
and a twisting segment is first rolled by α about its base z axis: T = Rz(α)·T_cc.
s and f are evaluated as functions of φ² with a Taylor branch near 0 (double-``where``), so
values and gradients are finite at the straight configuration. No atan2, no division by φ.

Shapes: features (..., m, 4) with columns (ρ_re [m], ρ_im [m], β [m], α [rad]); poses are
homogeneous (..., 4, 4) [m]. Columns a segment does not actuate are ignored (β = l, α = 0).
"""
from __future__ import annotations

import functools

import torch
from torch import Tensor

from .checks import check_tensor
from .lie import (
    chain_components,
    chain_products,
    dense,
    exp_components,
    exp_components_and_tangents,
    pose_of_components,
    roll_components,
)
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


def cc_pose_and_jacobian(spec: RobotSpec, features: Tensor,
                         columns: list[tuple[int, int]] | None = None) -> tuple[Tensor, Tensor]:
    """Tip pose and its Jacobian w.r.t. feature columns, in closed form (the kernel's exponential with
    tangents and chain rule, :mod:`~.lie`): features (..., m, 4) → pose (..., 4, 4) [m] and J: the tip point's
    velocity [m] and angular velocity [rad] in the base frame per unit of each column. ``columns``: None for
    every (ρ_re, ρ_im, β, α) of every segment, J (..., 6, m, 4), columns a segment does not actuate zero; or a
    list of (segment, column index 0–3) pairs, J (..., 6, len(columns)) (e.g. the actuated features).

    Computed in the kernel's component form with the segments in front, (m, ...): the twist of segment k is
    ξ = (0, 0, β; −u_y, u_x, 0) with u = ρ/d, so its directions along (ρ_re, ρ_im, β) are the sparse constants
    dω_y = 1/d, dω_x = −1/d, dv_z = [extends] (a few operations each), and along α the roll's own velocity
    (:func:`~.lie.roll_components`).
    """
    u, beta, alpha = _segment_parameters(spec, features)
    radius, _, extends, twists = _segment_constants(spec, features.dtype, features.device)
    m, lead, dtype = spec.num_segments, beta.shape[:-1], features.dtype
    per_seg = lambda c: c.to(dtype).view(m, *([1] * len(lead)))  # noqa: E731   (m,) → (m, 1…)
    front = lambda x: x.movedim(-1, 0).contiguous()  # noqa: E731              (..., m) → (m, ...)
    ux, uy, b = front(u[..., 0]), front(u[..., 1]), front(beta)
    inv_d = per_seg(1 / radius)
    basis = [((None, None, None), (None, inv_d, None)), ((None, None, None), (-inv_d, None, None)),
             ((None, None, per_seg(extends)), (None, None, None)), ((None, None, None), (None, None, None))]
    wanted = [(k, c) for k in range(m) for c in range(4)] if columns is None else list(columns)
    # only the directions some wanted column uses (α only with a roll, β only where a segment extends)
    used = [c for c in range(4) if any(cc == c for _, cc in wanted) and (c != 3 or alpha is not None)
            and (c != 2 or any(s.extends for s in spec.segments))]
    rot, pos, tangents = exp_components_and_tangents((None, None, b), (-uy, ux, None), [basis[c] for c in used])
    if alpha is not None:
        rot, pos, tangents = roll_components(front(alpha), rot, pos, tangents, (used.index(3), per_seg(twists)))
    like = b[0]
    seg = lambda c, k: tuple(None if x is None else x[k] for x in c)  # noqa: E731

    def stacked(vectors: list, k: int) -> tuple:     # segment k's vectors of the used directions → components (T, ...)
        parts = [[seg(v, k)[i] for v in vectors] for i in range(3)]
        return tuple(None if all(p is None for p in c) else torch.stack(dense(c, like), dim=0) for c in parts)

    tip_rot, tip_pos, cols = chain_components(        # the chain rotates the directions of a segment together
        [seg(rot, k) for k in range(m)], [seg(pos, k) for k in range(m)],
        [[(stacked([a for a, _ in tangents], k), stacked([v for _, v in tangents], k))] for k in range(m)])
    zero = torch.zeros_like(like)
    entries = []                                      # row-major (6, columns), each (...): one stack at the end
    for i in range(6):
        for k, c in wanted:
            comp = (cols[k][0][0] + cols[k][0][1])[i] if c in used else None
            entries.append(zero if comp is None else comp[used.index(c)])
    jac = torch.stack(entries, dim=-1).unflatten(-1, (6, len(wanted)))
    if columns is None:
        jac = jac.unflatten(-1, (m, 4))
    return pose_of_components(tip_rot, tip_pos), jac


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
