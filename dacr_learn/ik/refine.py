"""The Levenberg–Marquardt refinement of IK starts, batched, with the limits inside the step (docs/ik.md).

Residual r = ((p − p*)/L, log(R·R*ᵀ)): the position error in units of the robot length L and the rotation vector
[rad] in the base frame (the position only when the target has no rotation); its Jacobian is the model's tip
Jacobian with the position rows divided by L. Each step holds the limits that block descent and projects the trial
point onto the admissible set (:func:`limited_step`); λ shrinks after an accepted step and grows after a rejected
one (:class:`Refinement`). :func:`levenberg_marquardt` refines given starts; :mod:`.solver` adds the starts.
"""
from __future__ import annotations

import math

import torch
from pytorch_kinematics.transforms import matrix_to_axis_angle
from torch import Tensor

from ..checks import F64
from ..limits import Limits
from .adapters import SolverModel


def fused_matmul(a: Tensor, b: Tensor) -> Tensor:
    """a·b of small matrices (..., n, k)·(..., k, p) as a broadcast multiply-sum: in an exported module Inductor
    fuses it with its neighbours instead of calling BLAS (a library call per tiny product at batch 1); in eager
    mode torch.matmul is faster."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def residual(model: SolverModel, x: Tensor, position: Tensor, rotation: Tensor | None, matmul=torch.matmul):
    """Residual r (M, 3 or 6) [units of L, rad], its Jacobian (M, 3 or 6, D), position and rotation errors (M,).
    ``matmul``: the product of small matrices (:func:`fused_matmul` in exported modules)."""
    pos, rot, jac = model.tip_and_jacobian(x)
    dp = (pos - position) / model.length
    pos_err = torch.linalg.vector_norm(pos - position, dim=-1)
    if rotation is None:
        return dp, jac[:, :3] / model.length, pos_err, torch.zeros_like(pos_err)
    rvec = matrix_to_axis_angle(matmul(rot, rotation.mT))              # log(R·R*ᵀ), base frame
    r = torch.cat([dp, rvec], dim=-1)
    jac = torch.cat([jac[:, :3] / model.length, jac[:, 3:]], dim=1)
    return r, jac, pos_err, torch.linalg.vector_norm(rvec, dim=-1)


class Refinement:
    """The LM state of M starts (module docstring): variables x (M, D), residual r and its Jacobian, cost ‖r‖²,
    damping λ and the errors, with the targets of each row.

    ``extra`` (e.g. :class:`~.collision.Avoidance`): a further condition on a solution, with ``triage(x)`` →
    (satisfied (M,) bool, failed by little (M,) bool) and ``residual(x)`` → (rows (M, E), Jacobian (M, E, D),
    satisfied (M,)), E = ``extra.rows``. A start whose tip has converged is checked; if the condition fails by
    little, the start is *hinged*: from then on its residual carries the extra rows (zeros for the other starts)
    and it converges when its tip has and the condition holds; if it fails by much, the start stalls (a new
    start is cheaper). So only the starts that need it pay for the extra rows."""

    def __init__(self, model: SolverModel, x0: Tensor, position: Tensor, rotation: Tensor | None,
                 tolerance: tuple[float, float], damping: float, extra=None):
        self.model, self.lim, self.damping, self.extra = model, model.limits, damping, extra
        self.position, self.rotation = position, rotation
        self.scale = self.lim.scale.to(F64)
        self.tol = tuple(0.1 * t for t in tolerance)                         # aim a decade below the tolerance
        self.x = self.lim.project(x0.to(F64))
        m = self.x.shape[0]
        self.hinged = torch.zeros(m, dtype=torch.bool)
        self.satisfied = torch.full((m,), extra is None)
        self.r, self.jac, self.pos_err, self.rot_err = self._residual(self.x, torch.arange(m))
        self.cost = (self.r * self.r).sum(-1)
        self.lam = torch.full_like(self.cost, damping)
        self._settle(torch.arange(m))

    def _residual(self, x: Tensor, rows: Tensor):
        r, jac, pos_err, rot_err = residual(self.model, x, self.position[rows],
                                            None if self.rotation is None else self.rotation[rows])
        self.tip_rows = r.shape[-1]
        if self.extra is None:
            return r, jac, pos_err, rot_err
        r_e, jac_e = r.new_zeros(r.shape[0], self.extra.rows), jac.new_zeros(r.shape[0], self.extra.rows, x.shape[1])
        self._satisfied_new = self.satisfied[rows].clone()
        h = self.hinged[rows].nonzero().squeeze(-1)
        if h.numel():
            r_e[h], jac_e[h], self._satisfied_new[h] = self.extra.residual(x[h])
        return torch.cat([r, r_e], -1), torch.cat([jac, jac_e], 1), pos_err, rot_err

    def _tip_converged(self) -> Tensor:
        return (self.pos_err <= self.tol[0]) & (self.rot_err <= self.tol[1])

    def converged(self) -> Tensor:
        return self._tip_converged() & self.satisfied

    def _settle(self, rows: Tensor) -> None:
        """Check the extra condition of the given rows whose tip has converged: those that fail it by little
        (``extra.triage``) are hinged, the others stall (their slot restarts from a new start)."""
        if self.extra is None:
            return
        rows = rows[self._tip_converged()[rows] & ~self.satisfied[rows] & ~self.hinged[rows]]
        if rows.numel() == 0:
            return
        ok, near = self.extra.triage(self.x[rows])
        self.satisfied[rows[ok]] = True
        self.lam[rows[~ok & ~near]] = math.inf
        bad = rows[~ok & near]
        if bad.numel():
            self.hinged[bad] = True
            self.r[bad], self.jac[bad], _, _ = self._residual(self.x[bad], bad)
            self.cost[bad] = (self.r[bad] * self.r[bad]).sum(-1)
            self.lam[bad] = self.damping

    def append(self, x0: Tensor, position: Tensor, rotation: Tensor | None) -> None:
        """New rows: starts x0 (R, D) towards their targets (position (R, 3), rotation (R, 3, 3) or None)."""
        first = self.x.shape[0]
        self.position = torch.cat([self.position, position])
        self.rotation = None if rotation is None else torch.cat([self.rotation, rotation])
        x = self.lim.project(x0.to(F64))
        self.hinged = torch.cat([self.hinged, torch.zeros(x.shape[0], dtype=torch.bool)])
        self.satisfied = torch.cat([self.satisfied, torch.full((x.shape[0],), self.extra is None)])
        new = torch.arange(first, first + x.shape[0])
        r, jac, pe, re = self._residual(x, new)
        self.x, self.r, self.jac = torch.cat([self.x, x]), torch.cat([self.r, r]), torch.cat([self.jac, jac])
        self.pos_err, self.rot_err = torch.cat([self.pos_err, pe]), torch.cat([self.rot_err, re])
        self.cost = torch.cat([self.cost, (r * r).sum(-1)])
        self.lam = torch.cat([self.lam, torch.full_like(pe, self.damping)])
        self._settle(new)

    def step(self, rows: Tensor) -> None:
        """One LM iteration of the given rows: a step with the limits inside it, kept if it lowers the cost."""
        la = self.lam[rows]
        xt = limited_step(self.lim, self.x[rows], self.r[rows], self.jac[rows], la, only_held=True)
        rt, jt, pe, re = self._residual(xt, rows)
        ct = (rt * rt).sum(-1)
        better = ct < self.cost[rows]
        current = self.x[rows], self.r[rows], self.jac[rows], self.pos_err[rows], self.rot_err[rows]
        kept, self.cost[rows], self.lam[rows] = lm_accept(current, (xt, rt, jt, pe, re), self.cost[rows], ct, la)
        self.x[rows], self.r[rows], self.jac[rows], self.pos_err[rows], self.rot_err[rows] = kept
        if self.extra is not None:
            self.satisfied[rows[better]] = self._satisfied_new[better]
        self._settle(rows)


def lm_iteration(model: SolverModel, state: tuple[Tensor, ...], position: Tensor, rotation: Tensor | None,
                 solve=None, matmul=torch.matmul, only_held: bool = True) -> tuple[Tensor, ...]:
    """One LM iteration of every row of ``state`` = (x (M, D), r (M, R), J (M, R, D), cost (M,), λ (M,), pos_err
    (M,) [m], rot_err (M,) [rad]) towards targets position (M, 3) [m] and rotation (M, 3, 3) or None: the step of
    :meth:`Refinement.step` on whole tensors (no row gathers or scatters; no extra condition), returning the new
    state. The working batch of :mod:`.pool` and the exported refinement run on it; ``solve``, ``matmul`` and
    ``only_held`` as in :func:`limited_step` (the compiled iteration of :mod:`.fused` passes the unrolled forms)."""
    x, r, jac, cost, lam, pos_err, rot_err = state
    xt = limited_step(model.limits, x, r, jac, lam, only_held=only_held, solve=solve, matmul=matmul)
    rt, jt, pe, re = residual(model, xt, position, rotation, matmul=matmul)
    (x, r, jac, pos_err, rot_err), cost, lam = lm_accept((x, r, jac, pos_err, rot_err), (xt, rt, jt, pe, re), cost,
                                                         (rt * rt).sum(-1), lam)
    return x, r, jac, cost, lam, pos_err, rot_err


def lm_accept(current: tuple[Tensor, ...], trial: tuple[Tensor, ...], cost: Tensor, trial_cost: Tensor,
              lam: Tensor) -> tuple[tuple[Tensor, ...], Tensor, Tensor]:
    """The LM acceptance rule of M rows: each row keeps its trial (every tensor of ``trial``, (M, ...), against the
    same of ``current``) where the trial cost (M,) is below the current cost, else its current values; λ (M,)
    shrinks to λ/3 (not below 1e-12) after an accepted step and grows to 4λ after a rejected one. Branch-free
    (torch.where), so exported modules use it too. Returns (the kept tensors, cost, λ)."""
    better = trial_cost < cost
    kept = tuple(torch.where(better[(...,) + (None,) * (t.dim() - 1)], t, c)
                 for c, t in zip(current, trial, strict=True))
    return kept, torch.where(better, trial_cost, cost), torch.where(better, torch.clamp(lam / 3, min=1e-12), lam * 4)


def spd_solve_unrolled(a: Tensor, b: Tensor) -> Tensor:
    """x (..., n) with a·x = b for symmetric positive definite a (..., n, n), by an LDLᵀ factorisation written out
    entry by entry (n is small: 3 or 6). For exported modules: AOTInductor fuses these elementwise operations into
    one kernel, while torch.linalg.solve has no compiled CPU shim in torch 2.13 and runs through its slow proxy
    executor. In eager mode prefer torch.linalg.solve."""
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]
    diag = []
    for j in range(n):
        d = a[..., j, j]
        for k in range(j):
            d = d - low[j][k] * low[j][k] * diag[k]
        diag.append(d)
        for i in range(j + 1, n):
            v = a[..., i, j]
            for k in range(j):
                v = v - low[i][k] * low[j][k] * diag[k]
            low[i][j] = v / d
    y = []
    for i in range(n):                                                  # L·y = b
        v = b[..., i]
        for k in range(i):
            v = v - low[i][k] * y[k]
        y.append(v)
    x = [None] * n
    for i in reversed(range(n)):                                        # D·Lᵀ·x = y
        v = y[i] / diag[i]
        for k in range(i + 1, n):
            v = v - low[k][i] * x[k]
        x[i] = v
    return torch.stack(x, dim=-1)


def limited_step(lim: Limits, x: Tensor, r: Tensor, jac: Tensor, lam: Tensor, only_held: bool = False,
                 solve=None, matmul=torch.matmul) -> Tensor:
    """The LM trial point of variables x (M, D) with residual r (M, R) and Jacobian ∂r/∂x (M, R, D), damping λ (M,):
    in scaled variables z = x/s, the limits that block descent are held (:func:`free_jacobian`: projector P),
    δz = −(J̃P)ᵀ(J̃PJ̃ᵀ + λI)⁻¹r minimises ‖r + J̃P·δz‖² + λ‖δz‖², and x + s·δz is projected onto the admissible set.
    ``only_held``: build P only for the rows some limit holds (data-dependent; False in exported modules, where
    every row takes the projector). ``solve``: (a, b) → a⁻¹b for the SPD system
    (default torch.linalg.solve; exported modules pass :func:`spd_solve_unrolled`) and ``matmul`` the products
    (exported modules: :func:`fused_matmul`)."""
    scale = lim.scale.to(x)
    ja = jac * scale
    ja, _ = free_jacobian(lim, x, ja, (ja.mT * r.unsqueeze(-2)).sum(-1), only_held, matmul)          # J̃ᵀr
    gram = matmul(ja, ja.mT) + lam[:, None, None] * torch.eye(r.shape[-1], dtype=x.dtype, device=x.device)
    y = torch.linalg.solve(gram, r.unsqueeze(-1)).squeeze(-1) if solve is None else solve(gram, r)
    step = -(ja.mT * y.unsqueeze(-2)).sum(-1)                                                # J̃ᵀy
    return lim.project(x + step * scale)


def free_jacobian(lim: Limits, x: Tensor, ja: Tensor, gradient: Tensor, only_held: bool = False,
                  matmul=torch.matmul) -> tuple[Tensor, Tensor | None]:
    """The limits inside a step, in scaled variables z = x/s: at variables x (M, D), with J̃ (M, R, D) and the
    gradient J̃ᵀr (M, D) of the cost (descent along −J̃ᵀr), the limits that block descent are held
    (:meth:`~dacr_learn.limits.Limits.blocked`) and their directions removed from J̃ by the projector P
    (:meth:`~.limits.Limits.free_directions`). Returns (J̃P (M, R, D), P (M, D, D)); with ``only_held`` P is not
    formed: J̃P = J̃·diag(free) − Σ (J̃n)nᵀ over the blocked disk normals n, a few whole-tensor operations (J̃
    unchanged where no limit holds), and None is returned for P. ``matmul``: as in :func:`limited_step`."""
    box, normals = lim.blocked(x, gradient)
    if not only_held:
        free = lim.free_directions(box, normals)
        return matmul(ja, free), free
    held = ja * (~box).to(ja.dtype).unsqueeze(-2)
    if normals is not None:                 # − (J̃n)nᵀ per blocked disk, n (M, D) zero off the disks and where free
        first, second = lim.disks.unbind(-1)
        disk_of = torch.zeros(lim.num_variables, dtype=torch.long, device=x.device)
        disk_of[first] = disk_of[second] = torch.arange(first.numel(), device=x.device)
        n = torch.zeros_like(x).index_copy(-1, lim.disks.flatten(), normals.flatten(-2)).unsqueeze(-2)  # (M, 1, D)
        a = ja * n
        along = a.index_select(-1, first) + a.index_select(-1, second)                # J̃n (M, R, k)
        held = held - along.index_select(-1, disk_of) * n
    return held, None


STALL_LAMBDA = 1e6   # λ beyond which a start has no descent direction left (a local minimum, or unreachable)


def levenberg_marquardt(model: SolverModel, x0: Tensor, position: Tensor, rotation: Tensor | None,
                        tolerance: tuple[float, float] = (1e-6, 1e-5), damping: float = 1e-3,
                        max_iterations: int = 25) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Refine M starts x0 (M, D) towards targets (position (M, 3) [m], rotation (M, 3, 3) or None) inside the
    limits (module docstring), at most ``max_iterations`` each. Returns (x (M, D), pos_err (M,) [m],
    rot_err (M,) [rad], iterations (M,)). A start stops when both errors are below a tenth of the tolerance or
    when λ exceeds :data:`STALL_LAMBDA`; x always stays admissible."""
    state = Refinement(model, x0, position, rotation, tolerance, damping)
    iters = torch.zeros(state.x.shape[0], dtype=torch.long)
    for _ in range(max_iterations):
        rows = (~state.converged() & (state.lam < STALL_LAMBDA)).nonzero().squeeze(-1)
        if rows.numel() == 0:
            break
        state.step(rows)
        iters[rows] += 1
    return state.x, state.pos_err, state.rot_err, iters
