"""The fixed arc-length grid of the RK4 integration: uniform steps per segment plus exact break points.

Each segment [ends_k, ends_k+1] gets ``steps`` equal RK4 steps; arc positions where a point load acts
or where the caller wants a station are inserted as extra nodes (splitting a step), so every jump and
every station is a node. Positions within 1e-12·L of a node are snapped onto it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class ArcGrid:
    """intervals: (s_a, s_b, segment index) of each RK4 step [m]; ends: segment boundaries (m + 1) [m];
    load_arcs: arc of each point load, snapped onto its node [m]; steps: uniform steps per segment;
    nodes: (K,) float64 arc of every node [m], K = len(intervals) + 1."""

    intervals: tuple[tuple[float, float, int], ...]
    ends: tuple[float, ...]
    load_arcs: tuple[float, ...]
    steps: int

    @property
    def nodes(self) -> Tensor:
        return torch.tensor([0.0] + [b for _, b, _ in self.intervals], dtype=torch.float64)

    def index(self, arcs: Sequence[float]) -> list[int]:
        """Node indices of the arcs (each within 1e-12·L of a node; ValueError otherwise)."""
        nodes, scale = self.nodes, self.ends[-1]
        out = []
        for a in arcs:
            i = int(torch.argmin((nodes - a).abs()))
            if abs(float(nodes[i]) - a) > 1e-12 * scale:
                raise ValueError(f"stations: got arc {a!r} m, expected a node of the grid (pass it as a station)")
            out.append(i)
        return out


def arc_grid(ends: Sequence[float], steps: int, load_arcs: Sequence[float] = (),
             stations: Sequence[float] = ()) -> ArcGrid:
    """The grid for segment boundaries ``ends`` (m + 1,) [m], ``steps`` ≥ 1 RK4 steps per segment, point
    loads at ``load_arcs`` [m] in (0, L] and extra ``stations`` [m] in [0, L]."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps_per_segment: got {steps!r}, expected an integer >= 1")
    total = ends[-1]
    tol = 1e-12 * total
    for name, arcs, low in (("point_wrenches", load_arcs, 0.0), ("stations", stations, -tol)):
        for a in arcs:
            if not low < a <= total + tol:
                raise ValueError(f"{name}: got arc {a!r} m, expected a reference arc length in "
                                 f"{'(' if low == 0 else '['}0, {total}] m")
    intervals, snapped = [], {}
    for k in range(len(ends) - 1):
        a, b = ends[k], ends[k + 1]
        nodes = [a + (b - a) * j / steps for j in range(1, steps)] + [b]
        for x in (*load_arcs, *stations):
            if a + tol < x < b - tol and all(abs(x - n) > tol for n in nodes):
                nodes.append(x)
        nodes.sort()
        for x in (*load_arcs, *stations):
            near = [n for n in nodes if abs(n - x) <= tol]
            if near:
                snapped[x] = near[0]
        intervals += [(s0, s1, k) for s0, s1 in zip([a, *nodes[:-1]], nodes, strict=True)]
    return ArcGrid(tuple(intervals), tuple(ends), tuple(snapped[x] for x in load_arcs), steps)
