"""Shooting for the static Cosserat rod: Newton on the base wrench, implicit gradient (docs/cosserat.md §3).

The unknowns are the rod's internal force n(0) [N] and moment m(0) [N·m] at the base (body frame = robot base
frame), scaled to the dimensionless (n·L²/EI, m·L/EI), L the rod length; integrating ``rod.derivative`` leaves the
internal wrench beyond the tip, which must vanish (at disks and point loads the total wrench is continuous except
for the point load, ``rod.match_total_wrench``); converged where its largest scaled entry is ≤ ``tol``. The
Jacobian (forward differences on a coarser grid, Broyden updates, step halving: :func:`newton`) and the implicit
gradient (value z*, derivative −J⁻¹ ∂r/∂θ at z*): docs/cosserat.md §3.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .grid import ArcGrid
from .rod import STATE, Section, add_body_wrench, derivative, match_total_wrench, rk4, tendon_monomials, total_wrench
from .tendon import TendonRouting

FD_FORWARD, FD_CENTRAL = 1e-7, 2e-5   # difference steps of the dimensionless unknowns
REFRESH = 0.3                          # recompute J where a Newton step reduced ‖r‖ by less than this


class Loads:
    """Flattened loads of a batch of B problems, base frame: weight per length (B, 3) [N/m] or None and
    point wrenches (F [N], M [N·m]) (B, 6), one per ``grid.load_arcs`` entry."""

    def __init__(self, weight: Tensor | None, wrenches: list[Tensor]):
        self.weight, self.wrenches = weight, wrenches

    def select(self, idx: Tensor) -> Loads:
        return Loads(None if self.weight is None else self.weight[idx], [w[idx] for w in self.wrenches])

    def tensors(self) -> list[Tensor]:
        """The weight (if any) and the wrenches."""
        return ([] if self.weight is None else [self.weight]) + list(self.wrenches)

    def detached(self) -> Loads:
        return Loads(None if self.weight is None else self.weight.detach(), [w.detach() for w in self.wrenches])


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
            off = routing.offsets_in(k)[idx].to(x.dtype)
            plans[k] = (idx, off, tendon_monomials(off))
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
    kinks = routing.segment_offsets is not None       # tendons change radius at every segment boundary
    if not arcs and not (end and (routing.terminating(k).numel() or kinks)):
        return y
    before = routing.active(k)
    total = total_wrench(y, tension[:, before], routing.offsets_in(k)[before].to(y.dtype), section)
    rt = y[:, 3:12].reshape(-1, 3, 3).transpose(-1, -2)
    for wrench in arcs:
        total = total - torch.cat([rt @ wrench[:, :3, None], rt @ wrench[:, 3:, None]], dim=1).squeeze(-1)
    after, beyond = (routing.active(k + 1), k + 1) if end else (before, k)
    return match_total_wrench(y, total, tension[:, after], routing.offsets_in(beyond)[after].to(y.dtype), section)


def wrench_scale(section: Section, length: float) -> Tensor:
    """(6,) float64 (EI/L² [N] ×3, EI/L [N·m] ×3): the scale of the base unknowns and of the residual."""
    ei = section.bending_stiffness
    return torch.tensor([ei / length**2] * 3 + [ei / length] * 3, dtype=torch.float64)


def residual(end: Tensor, section: Section, length: float) -> Tensor:
    """Internal wrench beyond the tip (B, 6) over ``wrench_scale``, i.e. (n·L²/EI, m·L/EI) (dimensionless)."""
    wrench = torch.cat([section.kse.to(end.dtype) * end[:, 12:15], section.kbt.to(end.dtype) * end[:, 15:18]], -1)
    return wrench / wrench_scale(section, length).to(end.dtype)


def residual_and_jacobian(fun: Callable[[Tensor, Tensor], Tensor], x: Tensor, idx: Tensor,
                          central: bool = False) -> tuple[Tensor, Tensor]:
    """r = fun(x, idx) (B, 6) and the per-sample Jacobian ∂r/∂x (B, 6, 6) by finite differences, all
    evaluations in one batch (7 forward, 13 central). x and r are dimensionless, of order one: forward
    steps of 1e-7 leave an error ≈ 1e-7 (enough to steer Newton), central steps of 2e-5 ≈ 1e-10."""
    b, step = x.shape[0], (FD_CENTRAL if central else FD_FORWARD)
    eye = step * torch.eye(6, dtype=x.dtype)
    offsets = torch.cat([torch.zeros(1, 6, dtype=x.dtype), eye] + ([-eye] if central else []))
    r = fun((x.unsqueeze(0) + offsets.unsqueeze(1)).reshape(-1, 6), idx.repeat(offsets.shape[0]))
    r = r.reshape(offsets.shape[0], b, 6)
    diff = (r[1:7] - r[7:]) / (2 * step) if central else (r[1:7] - r[0]) / step
    return r[0], diff.permute(1, 2, 0)


Residual = Callable[[Tensor, Tensor], Tensor]
KeepingResidual = Callable[[Tensor, Tensor], "tuple[Tensor, Tensor | None]"]


def newton(fun: KeepingResidual, x0: Tensor, tol: float, max_iter: int, coarse: Residual | None = None,
           halvings: int = 10) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Damped quasi-Newton on r(x) = 0 per sample while it has not converged (docs/cosserat.md §3).

    ``fun(x, idx)`` → (r (n, 6), kept (n, ...) or None) for rows x of samples ``idx``; ``kept`` (e.g. node states)
    is returned for each sample's final x. J: forward differences of ``coarse`` (default ``fun``'s r), Broyden
    updates, refreshed where ‖r‖₂ fell by less than ``REFRESH``. Steps x − α·J⁻¹r, α = 1, 1/2, … (``halvings``
    tries, Armijo factor 1 − 1e-4·α), else the best trial if it lowers ‖r‖₂, else J is differenced again (on
    ``coarse``, then ``fun``) and a sample that still cannot move stops.
    Returns (x (B, 6), residual max-abs (B,) (inf where non-finite), steps taken (B,), kept (B, ...) or None).
    """
    x = x0.clone()
    every = torch.arange(x.shape[0])
    fine = lambda z, idx: fun(z, idx)[0]  # noqa: E731
    coarse, first = (fine, _FINE) if coarse is None else (coarse, _COARSE)
    r, kept = fun(x, every)
    jac = residual_and_jacobian(coarse, x, every)[1]
    res = _max_abs(r)
    iters = torch.zeros(x.shape[0], dtype=torch.long)
    fresh = torch.full((x.shape[0],), first)        # how J was last made: _UPDATED, _COARSE or _FINE differences
    todo = every[torch.isfinite(res) & (res > tol)]
    for _ in range(max_iter):
        if not todo.numel():
            break
        j, r0 = jac[todo], r[todo]
        step, info = torch.linalg.solve_ex(j, r0)
        step = torch.where((info == 0).unsqueeze(-1), step, torch.nan)
        x1, r1, k1, moved = _line_search(fun, x[todo], step, r0, None if kept is None else kept[todo], todo, halvings)
        dx, dr = x1 - x[todo], r1 - r0
        norm2 = (dx * dx).sum(-1, keepdim=True).clamp_min(torch.finfo(dx.dtype).tiny)
        broyden = j + ((dr - (j @ dx.unsqueeze(-1)).squeeze(-1)) / norm2).unsqueeze(-1) * dx.unsqueeze(-2)  # "good"
        j = torch.where(moved[:, None, None], broyden, j)
        was = fresh[todo]
        stalled = ~moved & (was == _FINE)
        again_fine = ~moved & (was == _COARSE)
        slow = (r1.norm(dim=-1) > REFRESH * r0.norm(dim=-1)) & torch.isfinite(r1).all(-1) & ~stalled & ~again_fine
        if slow.any():
            j[slow] = residual_and_jacobian(coarse, x1[slow], todo[slow])[1]
        if again_fine.any():
            j[again_fine] = residual_and_jacobian(fine, x1[again_fine], todo[again_fine])[1]
        fresh[todo] = torch.where(again_fine | stalled, _FINE, torch.where(slow, first, _UPDATED))
        x[todo], r[todo], jac[todo] = x1, r1, j
        if kept is not None:
            kept[todo] = k1
        iters[todo] += 1
        res[todo] = _max_abs(r1)
        todo = todo[torch.isfinite(res[todo]) & (res[todo] > tol) & ~stalled]   # NaN/inf: given up, reported as inf
    return x, res, iters, kept


_UPDATED, _COARSE, _FINE = 0, 1, 2


def _max_abs(r: Tensor) -> Tensor:
    norm = r.abs().amax(-1)
    return torch.where(torch.isfinite(norm), norm, torch.inf)


def _line_search(fun: KeepingResidual, x: Tensor, step: Tensor, r: Tensor, kept: Tensor | None, idx: Tensor,
                 halvings: int) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
    """(x', fun's r and kept at x', moved (n,) bool) per sample: x' = x − α·step with the first α = 2^-k
    (k < halvings) that decreases ‖r‖₂ by the Armijo factor (see newton); where none does, the trial of least
    ‖r‖₂ if that is below ‖r(x)‖₂, else x itself (moved False)."""
    norm = r.norm(dim=-1)
    best_x, best_r, best_norm = x.clone(), r.clone(), norm.clone()
    best_kept = None if kept is None else kept.clone()
    pending, alpha = torch.arange(x.shape[0]), 1.0
    for _ in range(halvings):
        trial = x[pending] - alpha * step[pending]
        tr, tk = fun(trial, idx[pending])
        tn = torch.where(torch.isfinite(tr).all(-1), tr.norm(dim=-1), torch.inf)
        ok = tn <= (1 - 1e-4 * alpha) * norm[pending]
        take = ok | (tn < best_norm[pending])
        rows = pending[take]
        best_x[rows], best_r[rows], best_norm[rows] = trial[take], tr[take], tn[take]
        if best_kept is not None:
            best_kept[rows] = tk[take]
        pending = pending[~ok]
        if not pending.numel():
            break
        alpha /= 2
    return best_x, best_r, best_kept, best_norm < norm
