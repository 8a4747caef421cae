"""Shooting for the static Cosserat rod: Newton on the base wrench, implicit gradient.

The unknowns are the rod's internal force n(0) [N] and moment m(0) [N·m] at the base (body frame =
robot base frame, z along the straight backbone). Integrating the ODE of ``rod.derivative`` from the
base leaves the internal wrench beyond the tip, which must vanish. At a disk where tendons end, and
where a point load acts, the total wrench carried by rod and tendons together is continuous except
for the point load (−Rᵀ[F; M]); the rod's strains beyond the disk follow from it
(``rod.match_total_wrench``, which includes the kink force of the tendons that pass through).
The residual is the wrench beyond the tip scaled to a dimensionless bending measure,
(n·L²/EI, m·L/EI), L the rod length; a sample has converged when its largest entry is ≤ ``tol``.
Newton's unknowns are scaled the same way, so both are of order one.

Jacobian (6×6 per sample): central differences, all 13 evaluations in one batch, step 2e-5 of
the scale (error ≈ 1e-10 relative). The residual itself is exact; J only steers Newton, whose
convergence stays quadratic down to the rounding level (about 1e-15 here). Damped by halving the
step until ‖r‖ decreases.

Gradient: Newton runs without a graph; at the solution z* one more Newton step
z = z* − J⁻¹·r(z*, θ) is taken with the graph on and J held fixed. Its value is z* (r ≈ 0) and its
derivative −J⁻¹ ∂r/∂θ is the implicit-function gradient (accurate to J's ≈ 1e-10), at the cost of
one integration with a graph instead of back-propagating through every iteration.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .grid import ArcGrid
from .rod import (
    STATE,
    Section,
    add_body_wrench,
    derivative,
    match_total_wrench,
    rk4,
    tendon_outer_products,
    total_wrench,
)
from .tendon import TendonRouting

FD_STEP = 2e-5


class Loads:
    """Flattened loads of a batch of B problems, base frame: weight per length (B, 3) [N/m] or None and
    point wrenches (F [N], M [N·m]) (B, 6), one per ``grid.load_arcs`` entry."""

    def __init__(self, weight: Tensor | None, wrenches: list[Tensor]):
        self.weight, self.wrenches = weight, wrenches

    def select(self, idx: Tensor) -> Loads:
        return Loads(None if self.weight is None else self.weight[idx], [w[idx] for w in self.wrenches])


def integrate(x: Tensor, tension: Tensor, loads: Loads, routing: TendonRouting, section: Section,
              grid: ArcGrid, keep_nodes: bool = True) -> tuple[list[Tensor], Tensor]:
    """States at every grid node (list of (B, 18 + T), before the jumps there; empty unless ``keep_nodes``)
    and the state beyond the tip (after all jumps), from the base wrench x = (n(0), m(0)) (B, 6) [N, N·m]
    and tensions (B, T) [N]."""
    b, t = tension.shape
    y = x.new_zeros(b, STATE + t)
    y[:, 3:12] = torch.eye(3, dtype=x.dtype).reshape(9)
    y = add_body_wrench(y, x, section)
    nodes, plans = [y] if keep_nodes else [], {}
    for a, s, k in grid.intervals:
        if k not in plans:
            idx = routing.active(k)
            off = routing.offsets[idx].to(x.dtype)
            plans[k] = (idx, off, tendon_outer_products(off))
        idx, off, outer = plans[k]
        tau = tension[:, idx]

        def f(z, tau=tau, off=off, outer=outer, idx=idx):
            return derivative(z, tau, off, outer, idx, section, loads.weight)

        y = rk4(f, y, s - a, 1)[0]
        if keep_nodes:
            nodes.append(y)
        y = _jumps(y, s, k, tension, loads, routing, section, grid)
    return nodes, y


def _jumps(y: Tensor, s: float, k: int, tension: Tensor, loads: Loads, routing: TendonRouting, section: Section,
           grid: ArcGrid) -> Tensor:
    """The state after arc s (in segment k), where tendons may end (s = end of segment k) and point loads
    may act: the total (rod + tendon) wrench drops by the point loads, −Rᵀ[F; M], and is otherwise
    continuous; the rod's strains follow from it with the tendons that continue (``match_total_wrench``)."""
    end = s == grid.ends[k + 1]
    arcs = [w for arc, w in zip(grid.load_arcs, loads.wrenches, strict=True) if arc == s]
    if not arcs and not (end and routing.terminating(k).numel()):
        return y
    before = routing.active(k)
    total = total_wrench(y, tension[:, before], routing.offsets[before].to(y.dtype), section)
    rt = y[:, 3:12].reshape(-1, 3, 3).transpose(-1, -2)
    for wrench in arcs:
        total = total - torch.cat([rt @ wrench[:, :3, None], rt @ wrench[:, 3:, None]], dim=1).squeeze(-1)
    after = routing.active(k + 1) if end else before
    return match_total_wrench(y, total, tension[:, after], routing.offsets[after].to(y.dtype), section)


def wrench_scale(section: Section, length: float) -> Tensor:
    """(6,) float64 (EI/L² [N] ×3, EI/L [N·m] ×3): the scale of the base unknowns and of the residual."""
    ei = section.bending_stiffness
    return torch.tensor([ei / length**2] * 3 + [ei / length] * 3, dtype=torch.float64)


def residual(end: Tensor, section: Section, length: float) -> Tensor:
    """Internal wrench beyond the tip (B, 6) over ``wrench_scale``, i.e. (n·L²/EI, m·L/EI) (dimensionless)."""
    wrench = torch.cat([section.kse.to(end.dtype) * end[:, 12:15], section.kbt.to(end.dtype) * end[:, 15:18]], -1)
    return wrench / wrench_scale(section, length).to(end.dtype)


def residual_and_jacobian(fun: Callable[[Tensor, Tensor], Tensor], x: Tensor, idx: Tensor,
                          step: float = FD_STEP) -> tuple[Tensor, Tensor]:
    """r = fun(x, idx) (B, 6) and the per-sample Jacobian ∂r/∂x (B, 6, 6) by central differences, all 13
    evaluations in one batch. x and r are dimensionless (base wrench and tip wrench over (EI/L², EI/L)),
    of order one, so the truncation error ~ step² and the rounding error ~ eps/step are both ≈ 1e-10."""
    b = x.shape[0]
    eye = torch.eye(6, dtype=x.dtype)
    offsets = torch.cat([torch.zeros(1, 6, dtype=x.dtype), step * eye, -step * eye])   # (13, 6)
    r = fun((x.unsqueeze(0) + offsets.unsqueeze(1)).reshape(-1, 6), idx.repeat(13)).reshape(13, b, 6)
    return r[0], (r[1:7] - r[7:]).permute(1, 2, 0) / (2 * step)


def newton(fun: Callable[[Tensor, Tensor], Tensor], x0: Tensor, tol: float, max_iter: int,
           halvings: int = 10) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Damped Newton on fun(x, idx) = 0 per sample (idx: the samples' rows), each sample on its own and
    only while it has not converged. Step x − α·J⁻¹r with α = 1, 1/2, … (``halvings`` tries, one plain
    evaluation each) until ‖r‖₂ decreases (Armijo factor 1 − 1e-4·α); without a decrease the smallest
    α is taken. Returns (x (B, 6), residual max-abs (B,) (inf where non-finite), Newton steps (B,),
    Jacobian at x (B, 6, 6))."""
    x = x0.clone()
    res = torch.full((x.shape[0],), torch.inf, dtype=x.dtype)
    iters = torch.zeros(x.shape[0], dtype=torch.long)
    jac = torch.eye(6, dtype=x.dtype).repeat(x.shape[0], 1, 1)
    todo = torch.arange(x.shape[0])
    for _ in range(max_iter + 1):
        r, j = residual_and_jacobian(fun, x[todo], todo)
        norm = r.abs().amax(-1)
        res[todo], jac[todo] = torch.where(torch.isfinite(norm), norm, torch.inf), j
        keep = torch.isfinite(norm) & (norm > tol) & (iters[todo] < max_iter)
        todo, r, j = todo[keep], r[keep], j[keep]
        if not todo.numel():
            break
        step, info = torch.linalg.solve_ex(j, r)
        step = torch.where((info == 0).unsqueeze(-1), step, torch.nan)
        x[todo] = _line_search(fun, x[todo], step, r.norm(dim=-1), todo, halvings)
        iters[todo] += 1
    return x, res, iters, jac


def _line_search(fun, x: Tensor, step: Tensor, norm: Tensor, idx: Tensor, halvings: int) -> Tensor:
    """x − α·step per sample with the first α = 2^-k (k < halvings) that decreases ‖fun‖₂ (see newton)."""
    alpha = torch.ones_like(norm)
    pending = torch.arange(x.shape[0])
    for k in range(halvings):
        trial = fun(x[pending] - alpha[pending, None] * step[pending], idx[pending]).norm(dim=-1)
        ok = torch.isfinite(trial) & (trial <= (1 - 1e-4 * alpha[pending]) * norm[pending])
        pending = pending[~ok]
        if not pending.numel() or k == halvings - 1:
            break
        alpha[pending] = alpha[pending] / 2
    return x - alpha.unsqueeze(-1) * step
