"""Static Cosserat rod with straight tendons: the ODE right-hand side and the RK4 integrator.

After Rucker & Webster (2011), "Statics and dynamics of continuum robots with general tendon routing and external
loading", IEEE T-RO 27(6), with straight routing (body-frame offsets r_i constant) and an initially straight,
unstrained rod (v* = e3, u* = 0): p' = R v, R' = R û, L_i' = ‖s_i‖ and

    (K + Σ_i E_i A_i E_iᵀ) [v'; u'] = [d; c],   d = −û K_se (v − e3) − Rᵀ f_e − Σ_i τ_i u × t_i,
                                                c = −û K_bt u − v̂ K_se (v − e3) − Σ_i τ_i r_i × (u × t_i)

(K, E_i, A_i, s_i = v + u × r_i, t_i = s_i/‖s_i‖, f_e and the wrench at disks: docs/cosserat.md §2). Internal force
n = K_se (v − e3) [N], moment m = K_bt u [N·m]. The flat state (B, 18 + T) is p (3) [m], R (9, row-major),
ε = v − e3 (3) (not v: keeps n = K_se ε precise for a stiff EA), u (3) [1/m] and the tendon path lengths L (T) [m].
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..lie import hat
from ..robot import MechanicsSpec

STATE = 18  # p, R, ε = v − e3, u; the T tendon path lengths follow
JUMP_NEWTON_STEPS = 4


@dataclass(frozen=True)
class Section:
    """Diagonal stiffnesses of the cross-section: kse = (GA, GA, EA) [N], kbt = (EI, EI, GJ) [N·m²];
    mass per length ρA [kg/m]. Shear coefficient 1, as in Rucker & Webster (2011)."""

    kse: Tensor
    kbt: Tensor
    mass_per_length: float

    @classmethod
    def from_mechanics(cls, mech: MechanicsSpec) -> Section:
        ro, ri = mech.outer_radius, mech.inner_radius
        area, inertia = math.pi * (ro**2 - ri**2), math.pi * (ro**4 - ri**4) / 4
        e, g = mech.youngs_modulus, mech.shear_modulus
        kse = torch.tensor([g * area, g * area, e * area], dtype=torch.float64)
        kbt = torch.tensor([e * inertia, e * inertia, g * 2 * inertia], dtype=torch.float64)
        return cls(kse, kbt, mech.density * area)

    @property
    def bending_stiffness(self) -> float:
        """EI [N·m²], the scale of the shooting residual."""
        return float(self.kbt[0])


def unpack(y: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(p (B, 3), R (B, 3, 3), v = ε + e3 (B, 3), u (B, 3)) of a flat state (B, 18 + T)."""
    return y[:, 0:3], y[:, 3:12].reshape(-1, 3, 3), y[:, 12:15] + y.new_tensor([0.0, 0.0, 1.0]), y[:, 15:18]


def cross(a: Tensor, b: Tensor) -> Tensor:
    """a × b for (..., 3) tensors, by components (torch.linalg.cross is several times slower on CPU)."""
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], dim=-1)


def tendon_wrench_directions(v: Tensor, u: Tensor, offsets: Tensor) -> tuple[Tensor, Tensor]:
    """Per tendon at offset r_i = (x_i, y_i, 0) (offsets (Ta, 3)): ‖s_i‖ (B, Ta) of s_i = v + u × r_i and the
    unit wrench w_i = [t_i; r_i × t_i] (B, Ta, 6) that a tension τ_i exerts where the tendon ends (body
    frame), t_i = s_i/‖s_i‖. Written by components for speed (r_z = 0 by tendon.py)."""
    rx, ry = offsets[:, 0], offsets[:, 1]
    vx, vy, vz = v[:, 0:1], v[:, 1:2], v[:, 2:3]
    ux, uy, uz = u[:, 0:1], u[:, 1:2], u[:, 2:3]
    sx, sy, sz = vx - uz * ry, vy + uz * rx, vz + ux * ry - uy * rx
    norm = torch.sqrt(sx * sx + sy * sy + sz * sz)
    tx, ty, tz = sx / norm, sy / norm, sz / norm
    return norm, torch.stack([tx, ty, tz, ry * tz, -rx * tz, rx * ty - ry * tx], dim=-1)


@functools.lru_cache(maxsize=8)
def _block_map(dtype: torch.dtype) -> Tensor:
    """(36, 36): E(r) X E(r)ᵀ, E(r) = [I; r̂], flattened, for X symmetric 3×3 and r = (x, y, 0), is bilinear in
    the 6 entries (xx, xy, xz, yy, yz, zz) of X and the monomials (1, x, y, x², xy, y²) of r; row 6·e + g
    holds the coefficient of entry e times monomial g. Fitted exactly at 6 points (degree ≤ 2)."""
    pts = torch.tensor([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1], [1, 1]], dtype=torch.float64)
    mono = torch.stack([torch.ones(6, dtype=torch.float64), pts[:, 0], pts[:, 1], pts[:, 0] ** 2,
                        pts[:, 0] * pts[:, 1], pts[:, 1] ** 2], dim=-1)                    # (6 points, 6)
    e = torch.cat([torch.eye(3, dtype=torch.float64).expand(6, 3, 3),
                   hat(torch.cat([pts, torch.zeros(6, 1, dtype=torch.float64)], -1))], dim=-2)   # (6, 6, 3)
    rows = []
    for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        x = torch.zeros(3, 3, dtype=torch.float64)
        x[i, j] = x[j, i] = 1.0
        rows.append(torch.linalg.solve(mono, (e @ x @ e.transpose(-1, -2)).reshape(6, 36)))   # (6 mono, 36)
    return torch.cat(rows).to(dtype)


def tendon_monomials(offsets: Tensor) -> Tensor:
    """(Ta, 6) monomials (1, x, y, x², xy, y²) of the tendon offsets, the constant part of the tendon block."""
    x, y = offsets[:, 0], offsets[:, 1]
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], dim=-1)


def tendon_block(v: Tensor, u: Tensor, tension: Tensor, offsets: Tensor,
                 monomials: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Σ_i E_i A_i E_iᵀ (B, 6, 6), A_i = (τ_i/‖s_i‖)(I − t_i t_iᵀ), for tendons at offsets (Ta, 3), tensions (B, Ta),
    ‖s_i‖ (B, Ta), w_i (B, Ta, 6), ``monomials`` = tendon_monomials(offsets): I − t tᵀ without cancellation
    (1 − t_z² = t_x² + t_y²), contracted with the monomials and mapped by ``_block_map`` (two small GEMMs)."""
    norm, w = tendon_wrench_directions(v, u, offsets)
    tx, ty, tz = w[..., 0], w[..., 1], w[..., 2]
    coef = tension / norm
    x = torch.stack([ty * ty + tz * tz, -tx * ty, -tx * tz, tx * tx + tz * tz, -ty * tz, tx * tx + ty * ty], 1)
    moments = (x * coef.unsqueeze(1)) @ monomials                                      # (B, 6, 6)
    return (moments.reshape(-1, 36) @ _block_map(v.dtype)).reshape(-1, 6, 6), norm, w


def derivative(y: Tensor, tension: Tensor, offsets: Tensor, monomials: Tensor, active: Tensor, section: Section,
               weight: Tensor | None) -> Tensor:
    """dy/ds (B, 18 + T) of the flat state y (B, 18 + T) along a stretch where the tendons ``active`` (Ta,)
    run, with tensions ``tension`` (B, Ta) [N] at offsets (Ta, 3) [m], ``monomials`` = tendon_monomials
    (Ta, 6), and weight per length f_e (B, 3) [N/m] in the base frame (None: weightless)."""
    _, rot, v, u = unpack(y)
    kse, kbt = section.kse.to(y.dtype), section.kbt.to(y.dtype)
    n, m = kse * y[:, 12:15], kbt * u
    d = -cross(u, n)
    c = -cross(u, m) - cross(v, n)
    if weight is not None:
        d = d - (rot * weight.unsqueeze(-1)).sum(-2)                                   # Rᵀ f_e
    system = torch.diag_embed(torch.cat([kse, kbt])).expand(y.shape[0], 6, 6)
    lengths = y.new_zeros(y.shape[0], y.shape[1] - STATE)
    if active.numel():
        block, norm, w = tendon_block(v, u, tension, offsets, monomials)
        system = system + block
        # Σ τ u × t_i = u × Σ τ t_i;  Σ τ r_i × (u × t_i) = u Σ τ (r_i·t_i) − Σ τ (r_i·u) t_i
        r_dot_u = u[:, :2] @ offsets[:, :2].T
        sums = torch.stack([tension, tension * r_dot_u], 1) @ w[..., :3]               # (B, 2, 3)
        r_dot_t = (tension * (w[..., 0] * offsets[:, 0] + w[..., 1] * offsets[:, 1])).sum(-1, keepdim=True)
        d = d - cross(u, sums[:, 0])
        c = c - (u * r_dot_t - sums[:, 1])
        lengths = lengths.index_copy(1, active, norm)
    lu, pivots, _ = torch.linalg.lu_factor_ex(system)
    dvu = torch.linalg.lu_solve(lu, pivots, torch.cat([d, c], dim=-1).unsqueeze(-1)).squeeze(-1)
    dp = (rot * v.unsqueeze(-2)).sum(-1)                                                 # R v
    r0, r1, r2 = rot.unbind(-1)                                                          # columns of R
    ux, uy, uz = u[:, 0:1], u[:, 1:2], u[:, 2:3]
    drot = torch.stack([uz * r1 - uy * r2, ux * r2 - uz * r0, uy * r0 - ux * r1], dim=-1)   # R û
    return torch.cat([dp, drot.reshape(-1, 9), dvu, lengths], dim=-1)


def total_wrench(y: Tensor, tension: Tensor, offsets: Tensor, section: Section) -> Tensor:
    """Wrench (B, 6) carried across the cross-section by the rod and the tendons (offsets (Ta, 3), tensions
    (B, Ta)) together, body frame: [K_se ε; K_bt u] + Σ_i τ_i w_i [N, N·m]."""
    rod = torch.cat([section.kse.to(y.dtype) * y[:, 12:15], section.kbt.to(y.dtype) * y[:, 15:18]], dim=-1)
    if not offsets.shape[0]:
        return rod
    _, _, v, u = unpack(y)
    return rod + (tension.unsqueeze(-1) * tendon_wrench_directions(v, u, offsets)[1]).sum(1)


def match_total_wrench(y: Tensor, total: Tensor, tension: Tensor, offsets: Tensor, section: Section,
                       iterations: int = JUMP_NEWTON_STEPS) -> Tensor:
    """The state with its strains (ε, u) replaced so that ``total_wrench`` with the tendons (offsets (Ta, 3),
    tensions (B, Ta)) equals ``total`` (B, 6): the jump across a disk. Implicit (passing tendons kink), solved by
    ``iterations`` Newton steps with the Jacobian of ``derivative``, contracting like (τ d²/EI)^(2^k) (batched)."""
    kk = torch.cat([section.kse, section.kbt]).to(y.dtype)
    if not offsets.shape[0]:
        return torch.cat([y[:, :12], total / kk, y[:, 18:]], dim=-1)
    monomials = tendon_monomials(offsets)
    y = torch.cat([y[:, :12], (total - (total_wrench(y, tension, offsets, section) - kk * y[:, 12:18])) / kk,
                   y[:, 18:]], dim=-1)
    for _ in range(iterations):
        _, _, v, u = unpack(y)
        block, _, _ = tendon_block(v, u, tension, offsets, monomials)
        step = torch.linalg.solve_ex(torch.diag_embed(kk) + block,
                                     total_wrench(y, tension, offsets, section) - total)[0]
        y = torch.cat([y[:, :12], y[:, 12:18] - step, y[:, 18:]], dim=-1)
    return y


def rk4(f: Callable[[Tensor], Tensor], y: Tensor, h: float, steps: int) -> list[Tensor]:
    """Classic fixed-step RK4 of y' = f(y) over ``steps`` steps of size h; the states after each step."""
    out = []
    for _ in range(steps):
        k1 = f(y)
        k2 = f(y + (h / 2) * k1)
        k3 = f(y + (h / 2) * k2)
        k4 = f(y + h * k3)
        y = y + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(y)
    return out


def add_body_wrench(y: Tensor, wrench: Tensor, section: Section) -> Tensor:
    """The state with the rod's internal wrench (n, m) raised by ``wrench`` (B, 6) [N, N·m] (body frame):
    ε += K_se⁻¹ Δn, u += K_bt⁻¹ Δm."""
    dvu = wrench / torch.cat([section.kse, section.kbt]).to(y.dtype)
    return torch.cat([y[:, :12], y[:, 12:18] + dvu, y[:, 18:]], dim=-1)
