"""The twist kernel of :mod:`dacr_learn.lie` in the (..., 4, 4) / (..., T, 3) tensor layout, piece by piece: the
exponential with its tangents, the roll, the chain product rule on given poses. The package calls the fused
kernel (:func:`lie.twist_chain_jacobian`); tests/test_lie.py checks each piece against autograd and
the fused kernel against their composition. The layout conversions are the kernel's own (its private helpers).
"""
from __future__ import annotations

import torch
from torch import Tensor

from dacr_learn.component_algebra import components
from dacr_learn.lie import (
    _chain,
    _directions,
    _rot_pos,
    exp_components_and_tangents,
    hat,
    pose_from_parts,
    pose_of_components,
    roll_components,
)


def hat_map(dtype: torch.dtype = torch.float64) -> Tensor:
    """(6, 16): the linear map ξ = (v, ω) ↦ ξ^ = [[ω^, v], [0, 0]] flattened row-major."""
    basis = torch.eye(6, dtype=dtype)
    return pose_from_parts(hat(basis[:, 3:]), basis[:, :3], basis.new_zeros(1, 4)).flatten(-2)



def _undirections(x: tuple[Tensor, ...]) -> Tensor:
    """k components (T, ...) → (..., T, k)."""
    return torch.stack(x, dim=-1).movedim(0, -2)



def twist_exp_and_tangents(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """exp of twists ξ = (v, ω) (..., 6) and its first derivative along T directions dξ (..., T, 6).

    Returns the pose T = exp(ξ^) (..., 4, 4) (:func:`lie.twist_exp`) and, per direction, the spatial tangent of T:
    the angular velocity b = vee(dR·Rᵀ) (..., T, 3) [rad per unit] and the velocity of the frame's origin
    dp (..., T, 3) [m per unit], so that dT = [[b^·R, dp], [0, 0]] (:func:`lie.exp_components_and_tangents`).
    """
    c, d = components(xi), _directions(dxi.expand(*xi.shape[:-1], *dxi.shape[-2:]))
    rot, pos, [(ang, lin)] = exp_components_and_tangents(c[:3], c[3:], [(d[:3], d[3:])])
    return pose_of_components(rot, pos), _undirections(ang), _undirections(lin)


def twist_exp_and_tangent(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor]:
    """exp of twists ξ (..., 6) (:func:`lie.twist_exp`, (..., 4, 4)) and its tangents as matrices (..., T, 4, 4)
    along dξ (..., T, 6): dT = [[b^·R, dp], [0, 0]] of :func:`twist_exp_and_tangents`."""
    pose, ang, lin = twist_exp_and_tangents(xi, dxi)
    drot = hat(ang) @ pose[..., None, :3, :3]
    return pose, pose_from_parts(drot, lin, lin.new_zeros(1, 4))


def roll_z_and_tangents(poses: Tensor, ang: Tensor, lin: Tensor, alpha: Tensor,
                        alpha_row: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rz(α)·T and its spatial tangents from those of T: poses (..., 4, 4), tangents ang, lin (..., T, 3)
    (:func:`twist_exp_and_tangents`), roll α (...) [rad], ``alpha_row`` (..., T, 1): 1 on the direction that
    is the roll angle itself, 0 elsewhere (:func:`lie.roll_components`)."""
    rot, pos = _rot_pos(poses)
    rows = alpha_row.expand(*poses.shape[:-2], *alpha_row.shape[-2:])[..., 0].movedim(-1, 0)
    tangents = [(_directions(ang), _directions(lin))]
    rot, pos, [(b, dp)] = roll_components(alpha, rot, pos, tangents, (0, rows))
    return pose_of_components(rot, pos), _undirections(b), _undirections(dp)


def chain_jacobian(poses: Tensor, ang: Tensor, lin: Tensor, base: Tensor | None = None,
                   point: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The chain product rule: tip pose and base-frame Jacobian of a product of transforms.

    poses (..., n, 4, 4): T_1 … T_n, each relative to the end of the previous one; ang, lin (..., n, T, 3):
    spatial tangents of each T_k in its own base frame (:func:`twist_exp_and_tangents`) along T directions
    each. Optional fixed ends (no tangents): ``base`` (..., 4, 4), a pose in front of T_1 (J is then in its
    base frame), and ``point`` (..., 3) [m], a point fixed in the frame of T_n (the tip is then that point).
    Returns the tip pose B·T_1⋯T_n·Trans(point) (..., 4, 4) and J (..., 6, n·T): per factor and direction,
    the velocity of the tip point (rows 0–2) and the angular velocity (rows 3–5), both in the base frame
    (:func:`lie.chain_components`).
    """
    return _chain(*_rot_pos(poses), _directions(ang), _directions(lin), base, point)


