"""Clarke transform and the linear joint-space maps of the DACR abstraction (docs/design.md §1).

Pure, batched, differentiable functions. Notation:

- ψ_i [rad], d_i [m]: polar location of joint i; d [m]: the segment's reference radius.
- A = M_P⁻¹ (n×2), rows a_i = (d_i/d)(cos ψ_i, sin ψ_i): Clarke coordinates → displacements.
- M_P = (AᵀA)⁻¹Aᵀ (2×n): the Clarke matrix, the exact left inverse of A (docs/design.md, erratum 4:
  the rows carry d_i/d; for symmetric joints M_P = (2/n)[cos ψ; sin ψ]).
- Joint lengths of a robot: q = B·w + q₀ (see :func:`joint_space_maps`).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .robot import RobotSpec


def clarke_matrix_inverse(psi: Tensor, radii: Tensor | None = None, ref_radius: Tensor | float | None = None) -> Tensor:
    """A = M_P⁻¹: Clarke coordinates → joint displacements.

    Args:
        psi: joint angles ψ, shape (..., n) [rad].
        radii: joint radii d_i, shape (..., n) [m]; None means all equal to ``ref_radius``.
        ref_radius: reference radius d [m]; defaults to the mean of ``radii``.
    Returns:
        (..., n, 2) with rows (d_i/d)(cos ψ_i, sin ψ_i).
    """
    a = torch.stack([torch.cos(psi), torch.sin(psi)], dim=-1)
    if radii is None:
        return a
    if radii.shape != psi.shape:
        raise ValueError(f"radii: expected shape {tuple(psi.shape)} like psi, got {tuple(radii.shape)}")
    ref = radii.mean(dim=-1, keepdim=True) if ref_radius is None else torch.as_tensor(ref_radius, dtype=radii.dtype)
    return a * (radii / ref).unsqueeze(-1)


def clarke_matrix(psi: Tensor, radii: Tensor | None = None, ref_radius: Tensor | float | None = None) -> Tensor:
    """M_P = (AᵀA)⁻¹Aᵀ, the Clarke matrix (exact left inverse of :func:`clarke_matrix_inverse`).

    Args: as :func:`clarke_matrix_inverse`. Returns: (..., 2, n).
    For symmetric joints (ψ_i = offset + 2π(i−1)/n, equal radii) this is (2/n)[cos ψ; sin ψ].
    """
    return torch.linalg.pinv(clarke_matrix_inverse(psi, radii, ref_radius))


class JointSpaceMaps(NamedTuple):
    """The constant matrices of q = B_ρ·ρ + C·h for a robot (float64).

    displacement: B_ρ, (N, 2m) — joint length per Clarke coordinate (ρ_re⁽ᵏ⁾, ρ_im⁽ᵏ⁾ interleaved).
    path: C, (N, m) — 1 where a joint runs along segment k (k = j independent, k ≤ j coupled).
    actuated: W = [B_ρ | C[:, extending]], (N, 2m + e) — the map of the unknowns w.
    actuated_pinv: W⁺, (2m + e, N) — the encoder's least-squares inverse.
    N is the number of joint lengths, m the number of segments, e of extending segments.
    """

    displacement: Tensor
    path: Tensor
    actuated: Tensor
    actuated_pinv: Tensor


def joint_space_maps(spec: RobotSpec) -> JointSpaceMaps:
    """Build the linear maps of docs/design.md §1 for independent or coupled routing.

    Coupled routing: q_i⁽ʲ⁾ = Σ_{k≤j} [h⁽ᵏ⁾ − (d_i⁽ʲ⁾/d⁽ᵏ⁾)(ρ_re⁽ᵏ⁾ cos ψ_i⁽ʲ⁾ + ρ_im⁽ᵏ⁾ sin ψ_i⁽ʲ⁾)].
    """
    m, n_total = spec.num_segments, spec.num_length_joints
    b_rho = torch.zeros(n_total, 2 * m, dtype=torch.float64)
    path = torch.zeros(n_total, m, dtype=torch.float64)
    row = 0
    for j, seg in enumerate(spec.segments):
        psi = torch.tensor(seg.joint_angles, dtype=torch.float64)
        radii = torch.tensor(seg.joint_radii, dtype=torch.float64)
        rows = slice(row, row + seg.num_joints)
        passed = range(j + 1) if spec.routing == "coupled" else (j,)
        for k in passed:
            b_rho[rows, 2 * k:2 * k + 2] = -clarke_matrix_inverse(psi, radii, spec.segments[k].radius)
            path[rows, k] = 1.0
        row += seg.num_joints
    extending = [k for k, s in enumerate(spec.segments) if s.extends]
    actuated = torch.cat([b_rho, path[:, extending]], dim=1)
    return JointSpaceMaps(b_rho, path, actuated, torch.linalg.pinv(actuated))
