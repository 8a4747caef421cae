"""Public entry point: static shapes of a tendon-driven robot by the Cosserat-rod model (docs/cosserat.md).

>>> sol = solve_statics(spec, tension)          # tension (..., T) [N], spec with a mechanics block
>>> sol.frames.shape, sol.tip.shape, sol.tendon_lengths.shape   # (..., K, 4, 4), (..., 4, 4), (..., T)
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
from torch import Tensor

from ..body import BodyPoints, body_layout, body_of_points, check_points_per_segment
from ..checks import check_tensor
from ..lie import pose_from_parts
from ..robot import RobotSpec
from .grid import ArcGrid, arc_grid
from .rod import Section, unpack
from .shooting import Loads, integrate, newton, residual, residual_and_jacobian, wrench_scale
from .tendon import tendon_routing

CHUNK = 2048  # samples solved together: bounds memory; per-sample time was flat from 1024 to 4096 (docs)
COARSE_JACOBIAN = 4   # Newton's finite-difference Jacobian is taken on a grid with 1/4 of the steps,
JACOBIAN_STEPS = 2    # but at least 2 per segment (one left J off by up to 1.1 %, 2: 0.07 %; docs/cosserat.md §3)


def jacobian_grid(grid: ArcGrid) -> ArcGrid:
    """The grid Newton's finite-difference Jacobian is taken on: ``grid`` with a quarter of its steps, at least
    JACOBIAN_STEPS per segment (the fine grid itself below that); the same loads, no stations."""
    return arc_grid(grid.ends, min(grid.steps, max(JACOBIAN_STEPS, grid.steps // COARSE_JACOBIAN)), grid.load_arcs)


class ConvergenceError(RuntimeError):
    """Raised by :func:`solve_statics` when samples did not converge (``on_failure="raise"``)."""


@dataclass(frozen=True)
class CosseratSolution:
    """The static equilibrium of a batch (...,) of problems, all in the robot base frame, SI units.

    frames (..., K, 4, 4): backbone pose at the grid nodes, arc (K,) [m]; tendon_lengths (..., T) [m]: path
    lengths to each termination; tendon_rest_lengths (..., T) [m]: L/(1 + c·τ); curvature u, stretch v
    (..., K, 3) [1/m], [-] (proximal value at a jump); base_wrench (..., 6): internal (n [N], m [N·m]) at the base;
    residual (...,): scaled max-abs shooting residual; converged (...,) bool (residual <= tol and an admissible
    shape); iterations (...,). Samples that did not converge hold NaN in frames, lengths, strains and base_wrench.
    """

    frames: Tensor
    arc: Tensor
    tendon_lengths: Tensor
    tendon_rest_lengths: Tensor
    curvature: Tensor
    stretch: Tensor
    base_wrench: Tensor
    residual: Tensor
    converged: Tensor
    iterations: Tensor
    grid: ArcGrid

    @property
    def tip(self) -> Tensor:
        """Tip pose (..., 4, 4)."""
        return self.frames[..., -1, :, :]

    def at(self, arcs: Sequence[float]) -> Tensor:
        """Frames (..., S, 4, 4) at reference arcs [m] that are grid nodes (``stations`` of the solve)."""
        return self.frames[..., self.grid.index(arcs), :, :]

    def body(self, spec: RobotSpec, points_per_segment: int | None = None) -> BodyPoints:
        """The rod's body (:mod:`dacr_learn.body` layout): its nodes at the fractions j/K of every segment,
        (..., 1 + m·K, 3) [m], base frame (NaN where the solve failed); ``spec``: the solved robot. K (None: the solve's
        ``steps_per_segment``) must divide the steps per segment (ValueError otherwise)."""
        k = self.grid.steps if points_per_segment is None else check_points_per_segment(points_per_segment)
        arcs, _ = body_layout(spec, k)
        if self.grid.steps % k or abs(float(arcs[-1]) - self.grid.ends[-1]) > 1e-12 * self.grid.ends[-1]:
            raise ValueError(f"points_per_segment: the solve has {self.grid.steps} nodes per segment of "
                             f"{spec.name!r}; expected a divisor of it, got {k}")
        return body_of_points(spec, self.frames[..., self.grid.index(arcs.tolist()), :3, 3], k)


def _loads(spec: RobotSpec, batch: torch.Size, section: Section, gravity, tip_wrench, point_wrenches):
    """(grid load arcs, Loads flattened to B) with inputs checked; base-frame vectors broadcast to batch."""
    dtype = torch.float64
    weight = None
    if gravity is not None:
        check_tensor(gravity, "gravity", (3,))
        if section.mass_per_length > 0:
            weight = (section.mass_per_length * gravity.to(dtype)).expand(*batch, 3).reshape(-1, 3)
    arcs, wrenches = [], []
    for j, item in enumerate(point_wrenches):
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise ValueError(f"point_wrenches[{j}]: got {item!r}, expected a pair (arc [m], wrench (..., 6))")
        arcs.append(float(item[0]))
        wrenches.append(item[1])
    if tip_wrench is not None:
        arcs.append(spec.total_length)
        wrenches.append(tip_wrench)
    for j, w in enumerate(wrenches):
        check_tensor(w, "tip_wrench" if tip_wrench is w else f"point_wrenches[{j}]", (6,))
    return arcs, Loads(weight, [w.to(dtype).expand(*batch, 6).reshape(-1, 6) for w in wrenches])


def _initial_guess(tension: Tensor, offsets: Tensor, loads: Loads, arcs: list[float], length: float) -> Tensor:
    """Base wrench (B, 6) of the straight rod: external loads carried to the base minus Σ τ_i [e3; r_i × e3]."""
    e3 = tension.new_tensor([0.0, 0.0, 1.0])
    n = tension.new_zeros(tension.shape[0], 3)
    m = torch.zeros_like(n)
    for s, w in zip(arcs, loads.wrenches, strict=True):
        n, m = n + w[:, :3], m + w[:, 3:] + torch.linalg.cross((s * e3).expand_as(n), w[:, :3])
    if loads.weight is not None:
        n = n + length * loads.weight
        m = m + torch.linalg.cross((length**2 / 2 * e3).expand_as(n), loads.weight)
    tendon = torch.cat([e3.expand_as(offsets), torch.linalg.cross(offsets, e3.expand_as(offsets))], dim=-1)
    return torch.cat([n, m], dim=-1) - tension @ tendon


def check_solve_arguments(spec: RobotSpec, on_failure: str) -> None:
    """ValueError unless the robot has a mechanics block and ``on_failure`` is "raise" or "flag"."""
    if spec.mechanics is None:
        raise ValueError("mechanics: got None, expected a mechanics block in the robot description")
    if on_failure not in ("raise", "flag"):
        raise ValueError(f"on_failure: got {on_failure!r}, expected 'raise' or 'flag'")


def solve_statics(spec: RobotSpec, tension: Tensor, *, gravity: Tensor | None = None, tip_wrench: Tensor | None = None,
                  point_wrenches: Sequence[tuple[float, Tensor]] = (), steps_per_segment: int = 16,
                  stations: Sequence[float] = (), tol: float = 1e-10, max_iter: int = 40,
                  on_failure: str = "raise", chunk_size: int = CHUNK, workers: int | None = None,
                  passing: str = "own") -> CosseratSolution:
    """Static shape under tendon tensions (..., T) [N] (joint-vector order) and loads, base frame: ``gravity`` (3,)
    or (..., 3) [m/s²] (through ``mechanics.density``), ``tip_wrench`` (..., 6) (F [N], M [N·m]), ``point_wrenches``
    [(arc [m], wrench (..., 6))]. Float64, ``chunk_size`` samples at a time, ``workers`` chunks at once in threads
    (default ``torch.get_num_threads()``; one at a time for a solve with a gradient); differentiable w.r.t.
    tensions and loads (implicit gradient, shooting.py). ``on_failure``: "raise" (ConvergenceError) or "flag" (NaN
    outputs, converged = False). ``passing``: "own" or "segment" (:func:`~.tendon.tendon_routing`)."""
    check_solve_arguments(spec, on_failure)
    for name, value in (("chunk_size", chunk_size), ("workers", workers)):
        if value is not None and (not isinstance(value, int) or value < 1):
            raise ValueError(f"{name}: got {value!r}, expected a positive integer")
    routing, section = tendon_routing(spec, passing), Section.from_mechanics(spec.mechanics)
    check_tensor(tension, "tension", (routing.num_tendons,))
    batch = tension.shape[:-1]
    arcs, loads = _loads(spec, batch, section, gravity, tip_wrench, point_wrenches)
    grid = arc_grid(routing.ends.tolist(), steps_per_segment, arcs, stations)
    tau = tension.to(torch.float64).reshape(-1, routing.num_tendons)
    graph = torch.is_grad_enabled() and any(t.requires_grad for t in (tau, *loads.tensors()))
    workers = 1 if graph else (workers or torch.get_num_threads())

    def solve(rows: slice):
        return _solve_flat(tau[rows], loads.select(rows), routing, section, grid, spec.total_length, tol, max_iter,
                           graph)

    parts = _map_chunks(solve, tau.shape[0], chunk_size, workers)
    states, x, res, iters = (torch.cat(z) for z in zip(*parts, strict=True))
    converged = res <= tol
    admissible = _admissible(states, routing.max_offset)
    ok = converged & admissible
    if on_failure == "raise" and not bool(ok.all()):
        raise ConvergenceError(
            f"solve_statics: of {ok.numel()} samples {int((~converged).sum())} did not converge to residual <= "
            f"{tol:g} in {max_iter} Newton steps (worst {float(res.max()):.3g}; inf = NaN) and "
            f"{int((converged & ~admissible).sum())} converged to an inadmissible shape (a tendon folding back "
            "or the rod compressed to zero, see docs/cosserat.md); reduce the tensions or loads, raise max_iter, "
            "or pass on_failure='flag' to reject them")
    return _solution(states, x, res, ok, iters, grid, tau, spec.mechanics.tendon_compliance, batch)


def _map_chunks(solve, n: int, chunk_size: int, workers: int) -> list:
    """``solve(rows)`` over slices of at most ``chunk_size`` of n rows, in order; with workers > 1 in that many
    threads (torch releases the GIL in its kernels), a multiple of ``workers`` equal chunks so the threads finish
    together. Gradient-free only: grad mode is per thread."""
    count = max(math.ceil(n / chunk_size), 1)
    if workers > 1 and n > 1:
        count = min(math.ceil(count / workers) * workers, n)
    size = max(math.ceil(n / count), 1)
    rows = [slice(i, i + size) for i in range(0, max(n, 1), size)]
    if workers == 1 or len(rows) == 1:
        return [solve(r) for r in rows]

    def solve_without_grad(r: slice):
        with torch.no_grad():
            return solve(r)

    with ThreadPoolExecutor(min(workers, len(rows))) as pool:
        return list(pool.map(solve_without_grad, rows))


def _solve_flat(tau: Tensor, loads: Loads, routing, section: Section, grid: ArcGrid, length: float, tol: float,
                max_iter: int, graph: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(states at the nodes (B, K, 18 + T), base wrench x (B, 6), residual (B,), Newton steps (B,)) of B problems;
    ``graph``: the outputs carry the implicit gradient w.r.t. the tensions and loads."""
    scale = wrench_scale(section, length)
    coarse = jacobian_grid(grid)
    tau_d, loads_d = tau.detach(), loads.detached()

    def fun(z, idx, tau=tau_d, loads=loads_d, grid=grid):   # dimensionless base wrench z = x / scale → residual
        end = integrate(z * scale, tau[idx], loads.select(idx), routing, section, grid, keep_nodes=False)[1]
        return residual(end, section, length)

    def fine(z, idx):     # ``fun`` on the fine grid, also keeping the states at the nodes (B, K, 18 + T)
        states, end = integrate(z * scale, tau_d[idx], loads_d.select(idx), routing, section, grid)
        return residual(end, section, length), torch.stack(states, dim=1)

    with torch.no_grad():
        x0 = _initial_guess(tau_d, routing.offsets_in(0), loads_d, list(grid.load_arcs), length)
        z, res, iters, nodes = newton(fine, x0 / scale, tol, max_iter, coarse=lambda z, idx: fun(z, idx, grid=coarse))
    if not graph:
        return nodes, z * scale, res, iters          # newton kept the nodes of each sample's final z (no extra pass)
    every = torch.arange(z.shape[0])
    with torch.no_grad():
        jac = residual_and_jacobian(fun, z, every, central=True)[1]
    x = (z - torch.linalg.solve_ex(jac, fun(z, every, tau, loads))[0]) * scale   # value z*, gradient −J⁻¹ ∂r/∂θ
    return torch.stack(integrate(x, tau, loads, routing, section, grid)[0], dim=1), x, res, iters


def _admissible(states: Tensor, max_offset: float) -> Tensor:
    """(B,) bool: at every node each tendon advances along the backbone, v_z − ‖u_xy‖·max d_i > 0 (no folded
    tendon path, no rod compressed to zero length); the straight-routing model has no meaning otherwise."""
    v_z = states[..., 14] + 1
    kappa = torch.linalg.vector_norm(states[..., 15:17], dim=-1)
    return (v_z - kappa * max_offset > 0).all(-1)


def _solution(states, x, res, converged, iters, grid, tau, compliance, batch) -> CosseratSolution:
    bad = ~converged
    states = torch.where(bad[:, None, None], torch.nan, states)
    p, rot, v, u = unpack(states.reshape(-1, states.shape[-1]))
    frames = pose_from_parts(rot, p).reshape(*batch, -1, 4, 4)
    lengths = states[:, -1, 18:]
    return CosseratSolution(
        frames=frames, arc=grid.nodes, tendon_lengths=lengths.reshape(*batch, -1),
        tendon_rest_lengths=(lengths / (1 + compliance * tau)).reshape(*batch, -1),
        curvature=u.reshape(*batch, -1, 3), stretch=v.reshape(*batch, -1, 3),
        base_wrench=torch.where(bad[:, None], torch.nan, x).reshape(*batch, 6), residual=res.reshape(batch),
        converged=converged.reshape(batch), iterations=iters.reshape(batch), grid=grid)
