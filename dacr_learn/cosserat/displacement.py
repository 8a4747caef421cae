"""Displacement-controlled statics: the shape of a tendon robot whose actuators set tendon lengths.

A displacement actuator fixes each tendon's *unstretched* length ℓ_i, not its tension: tendon i is either taut, its
path stretched to ℓ_i, or slack with τ_i = 0. With R_i(τ) = ``tendon_rest_lengths`` of :func:`~.statics.solve_statics`
and F_i(τ) = R_i(τ) − ℓ_i, the tensions solve τ ≥ 0, F(τ) ≤ 0, τ_i F_i(τ) = 0 for every i, by the chord method of
docs/cosserat.md §10 (each step the linearised complementarity problem exactly, :func:`solve_lcp`, then one
Cosserat solve). The solve is gradient-free (no autograd through it); its inputs are data, not parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..checks import check_tensor
from ..robot import RobotSpec
from .rod import Section
from .statics import ConvergenceError, CosseratSolution, check_solve_arguments, solve_statics
from .tendon import tendon_routing

LCP_ACTIVE_SET_STEPS = 25
_SAMPLE_FIELDS = ("frames", "tendon_lengths", "tendon_rest_lengths", "curvature", "stretch", "base_wrench",
                  "residual", "converged", "iterations")   # the per-sample fields of a CosseratSolution
MIN_STEP = 1 / 64        # a sample whose step was halved below this gives up (flagged / raised)
LCP_GAUSS_SEIDEL_SWEEPS = 400


@dataclass(frozen=True)
class DisplacementSolution:
    """Statics under commanded tendon lengths, batch (...,), SI units: statics (the CosseratSolution at the tensions
    found), tension (..., T) [N], compliance (..., T, T) [m/N] (A = −∂R/∂τ: a ``compliance_guess`` for a nearby
    solve), violation (...,) [m] (max |F_i| taut, max(F_i, 0) slack), converged (...,) bool, iterations (...,)."""

    statics: CosseratSolution
    tension: Tensor
    compliance: Tensor
    violation: Tensor
    converged: Tensor
    iterations: Tensor

    @property
    def tip(self) -> Tensor:
        return self.statics.tip


def tension_scale(spec: RobotSpec) -> float:
    """Tension [N] that bends the whole robot by about one radian: EI / (max tendon radius · length)."""
    routing = tendon_routing(spec)
    ei = Section.from_mechanics(spec.mechanics).bending_stiffness
    return ei / (routing.max_offset * spec.total_length)


def solve_lcp(a: Tensor, q: Tensor) -> Tensor:
    """τ (B, T) with τ ≥ 0, w = Aτ + q ≥ 0, τ·w = 0 for SPD A (B, T, T), q (B, T): primal-dual active-set iterations
    until the set repeats, then projected Gauss–Seidel for samples unsettled after ``LCP_ACTIVE_SET_STEPS``."""
    active = q < 0
    tau = torch.zeros_like(q)
    done = torch.zeros(q.shape[0], dtype=torch.bool)
    eye = torch.eye(q.shape[-1], dtype=q.dtype)
    for _ in range(LCP_ACTIVE_SET_STEPS):
        f = active.to(q.dtype)
        # rows/columns outside the set become identity: τ_S = −A_SS⁻¹ q_S, τ_rest = 0
        mat = a * f.unsqueeze(-1) * f.unsqueeze(-2) + eye * (1 - f).unsqueeze(-1)
        new_tau = torch.linalg.solve(mat, -(q * f).unsqueeze(-1)).squeeze(-1)
        w = (a @ new_tau.unsqueeze(-1)).squeeze(-1) + q
        tau = torch.where(done.unsqueeze(-1), tau, new_tau)
        new_active = torch.where(active, new_tau > 0, w < 0)
        settled = (new_active == active).all(-1)
        done = done | settled
        active = torch.where(done.unsqueeze(-1), active, new_active)
        if bool(done.all()):
            break
    if not bool(done.all()):
        rows = ~done
        t, aa, qq = tau[rows].clamp(min=0), a[rows], q[rows]
        diag = torch.diagonal(aa, dim1=-2, dim2=-1)
        for _ in range(LCP_GAUSS_SEIDEL_SWEEPS):
            for i in range(q.shape[-1]):
                wi = (aa[:, i, :] * t).sum(-1) + qq[:, i]
                t[:, i] = (t[:, i] - wi / diag[:, i]).clamp(min=0)
        tau[rows] = t
    return tau.clamp(min=0)


def _violation(f: Tensor, tau: Tensor) -> Tensor:
    """(B,) max over tendons of |F| where taut (τ > 0) and max(F, 0) where slack; inf where F is not finite."""
    v = torch.where(tau > 0, f.abs(), f.clamp(min=0)).amax(-1)
    return torch.where(torch.isfinite(v), v, torch.inf)


def solve_displacements(spec: RobotSpec, rest_lengths: Tensor, *, gravity: Tensor | None = None,
                        tension_guess: Tensor | None = None, compliance_guess: Tensor | None = None,
                        spring_lengths: Tensor | None = None, steps_per_segment: int = 8, tol: float = 1e-9,
                        max_iter: int = 30, on_failure: str = "raise", workers: int | None = None,
                        passing: str = "own") -> DisplacementSolution:
    """Static shape under commanded unstretched tendon lengths ``rest_lengths`` (..., T) [m] (joint-vector order) and
    the robot's weight (``gravity`` (3,) or (..., 3) [m/s²], base frame, as :func:`solve_statics`).
    ``spring_lengths`` (T,) or (..., T) [m]: each tendon a linear spring of that length L_s (R = L − c·L_s·τ instead
    of L/(1 + cτ), c = ``mechanics.tendon_compliance``); per-sample values let one call solve several parameter sets.
    ``tension_guess`` (..., T) [N], ``compliance_guess`` (..., T, T) [m/N]: warm start. ``tol`` [m]: the largest
    tendon-length violation accepted. ``on_failure``: "raise" | "flag"; ``passing``: as :func:`solve_statics`.
    Float64, no gradient.
    """
    check_solve_arguments(spec, on_failure)
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise ValueError(f"max_iter: got {max_iter!r}, expected a positive integer")
    if not tol > 0:
        raise ValueError(f"tol: got {tol!r}, expected a positive length [m]")
    routing = tendon_routing(spec, passing)
    t = routing.num_tendons
    check_tensor(rest_lengths, "rest_lengths", (t,))
    if not bool((rest_lengths > 0).all()):
        raise ValueError("rest_lengths: got a non-positive tendon length, expected lengths > 0 [m]")
    batch = rest_lengths.shape[:-1]
    ell = rest_lengths.detach().to(torch.float64).reshape(-1, t)
    n = ell.shape[0]
    if tension_guess is not None:
        check_tensor(tension_guess, "tension_guess", (t,))
        if tension_guess.shape != rest_lengths.shape:
            raise ValueError(f"tension_guess: got shape {tuple(tension_guess.shape)}, expected "
                             f"{tuple(rest_lengths.shape)} (that of rest_lengths)")
        tau = tension_guess.detach().to(torch.float64).reshape(-1, t).clamp(min=0).clone()
    else:
        tau = ell.new_zeros(n, t)
    spring = None
    if spring_lengths is not None:
        check_tensor(spring_lengths, "spring_lengths", (t,))
        if spring_lengths.shape not in ((t,), (*batch, t)) or not bool((spring_lengths > 0).all()):
            raise ValueError(f"spring_lengths: got shape {tuple(spring_lengths.shape)}, expected ({t},) or "
                             f"{(*batch, t)} positive lengths [m]")
        spring = spring_lengths.detach().to(torch.float64) * spec.mechanics.tendon_compliance
        spring = spring.reshape(-1, t) if spring.dim() > 1 else spring
    if gravity is not None:
        check_tensor(gravity, "gravity", (3,))
        if gravity.shape not in ((3,), (*batch, 3)):
            raise ValueError(f"gravity: got shape {tuple(gravity.shape)}, expected (3,) or {(*batch, 3)}")
        gravity = gravity.detach().to(torch.float64)
        gravity = gravity.reshape(-1, 3) if gravity.dim() > 1 else gravity
    per_sample = any(v is not None and v.dim() > 1 for v in (gravity, spring))
    h = 1e-4 * tension_scale(spec)
    kw = dict(steps_per_segment=steps_per_segment, on_failure="flag", workers=workers, passing=passing)

    def of_rows(value: Tensor | None, rows: Tensor | None, repeat: int = 1) -> Tensor | None:
        """A per-sample input (n, k) restricted to ``rows`` (None: all), each row repeated; shared ones as they are."""
        if value is None or value.dim() == 1:
            return value
        value = value if rows is None else value[rows]
        return value.repeat_interleave(repeat, 0) if repeat > 1 else value

    def rest(tensions: Tensor, rows: Tensor | None = None, repeat: int = 1) -> tuple[Tensor, CosseratSolution]:
        """Rest lengths R (B, T) at tensions (B, T) of the samples ``rows`` (None: all), each ``repeat`` times."""
        with torch.no_grad():
            sol = solve_statics(spec, tensions, gravity=of_rows(gravity, rows, repeat), **kw)
        if spring is None:
            return sol.tendon_rest_lengths, sol
        return sol.tendon_lengths - of_rows(spring, rows, repeat) * tensions, sol

    def chord(tensions: Tensor, rows: Tensor | None = None) -> Tensor:
        """A = −∂R/∂τ (B, T, T) by central differences (one-sided at τ_j < h), symmetrised, at tensions (B, T) of
        the samples ``rows`` (None: all)."""
        b = tensions.shape[0]
        eye = torch.eye(t, dtype=torch.float64)
        up = tensions.unsqueeze(1) + h * eye
        down = (tensions.unsqueeze(1) - h * eye).clamp(min=0)
        r_up, _ = rest(up.reshape(-1, t), rows, t)
        r_down, _ = rest(down.reshape(-1, t), rows, t)
        width = (up - down).diagonal(dim1=-2, dim2=-1)                                # (b, T)
        jac = -(r_up - r_down).reshape(b, t, t) / width.unsqueeze(-1)                 # row j: ∂R/∂τ_j
        jac = jac.mT
        return (jac + jac.mT) / 2

    if compliance_guess is not None:
        if compliance_guess.shape != (*batch, t, t):
            raise ValueError(f"compliance_guess: got shape {tuple(compliance_guess.shape)}, expected "
                             f"{(*batch, t, t)}")
        a = compliance_guess.detach().to(torch.float64).reshape(n, t, t).clone()
    elif tension_guess is None and not per_sample:   # every sample starts straight and unloaded: one chord serves all
        a = chord(tau[:1], torch.zeros(1, dtype=torch.long)).expand(n, t, t).clone()
    else:
        a = chord(tau)
    r, sol = rest(tau)
    f = r - ell
    viol = _violation(f, tau)
    iters = torch.zeros(n, dtype=torch.long)
    accepted = {name: getattr(sol, name).clone() for name in _SAMPLE_FIELDS}   # each sample's accepted shape
    step = torch.ones(n, dtype=torch.float64)
    for _ in range(max_iter):
        # a sample whose current shape failed (no finite lengths) or whose chord failed cannot take a step:
        # it stays unconverged (flagged or raised below) instead of feeding NaN to the next solve
        usable = torch.isfinite(f).all(-1) & torch.isfinite(a).flatten(1).all(-1) & (step >= MIN_STEP)
        todo = torch.nonzero((viol > tol) & usable).flatten()
        if not todo.numel():
            break
        tt, aa, ff = tau[todo], a[todo], f[todo]
        target = solve_lcp(aa, -ff - (aa @ tt.unsqueeze(-1)).squeeze(-1))
        trial = (tt + step[todo].unsqueeze(-1) * (target - tt)).clamp(min=0)
        trial = torch.where(torch.isfinite(trial).all(-1, keepdim=True), trial, tt)   # no step: retake the chord
        r1, sol1 = rest(trial, todo)
        f1 = r1 - ell[todo]
        v1 = _violation(f1, trial)
        better = v1 < viol[todo]
        iters[todo] += 1
        keep = todo[better]
        tau[keep], f[keep], viol[keep] = trial[better], f1[better], v1[better]
        for name, value in accepted.items():
            value[keep] = getattr(sol1, name)[better]
        worse = todo[~better]
        retake = todo[~better & torch.isfinite(v1)]          # a worse shape: retake the chord at the iterate
        if retake.numel():
            a[retake] = chord(tau[retake], retake)
        step[worse] = step[worse] / 2                        # a worse or failed shape: shorten the step
        step[keep] = torch.clamp(step[keep] * 2, max=1.0)
    statics = CosseratSolution(arc=sol.arc, grid=sol.grid,
                               **{name: value.reshape(*batch, *value.shape[1:]) for name, value in accepted.items()})
    converged = (viol <= tol).reshape(batch) & statics.converged
    if on_failure == "raise" and not bool(converged.all()):
        raise ConvergenceError(
            f"solve_displacements: of {n} samples {int((~converged).sum())} did not reach tendon lengths within "
            f"{tol:g} m in {max_iter} steps (worst {float(viol.max()):.3g} m); check that the commanded lengths "
            "are reachable (a tendon shortened far beyond what bends the robot), or pass on_failure='flag'")
    return DisplacementSolution(
        statics=statics, tension=tau.reshape(*batch, t), compliance=a.reshape(*batch, t, t),
        violation=viol.reshape(batch), converged=converged, iterations=iters.reshape(batch))


__all__ = ["DisplacementSolution", "solve_displacements", "solve_lcp", "tension_scale"]
