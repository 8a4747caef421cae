"""A path to follow: a polyline (W, 3) [m], its arc length, and points at given arc lengths.

The tip enters the path at ``points[0]`` and follows it to ``points[-1]``. :meth:`Path.at` interpolates linearly
between the vertices; an arc length below 0 lies on the straight **entry line** behind ``points[0]`` along the
path's initial direction (what the planner asks of the part of the body not yet inserted), one above the
length is clamped to the end. :meth:`Path.distance` is the exact distance of points to the polyline up to an
arc length (the traversed part). Float64 throughout.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import F64


class Path:
    """A polyline path (W, 3) [m], W ≥ 2, finite, no two consecutive points equal.

    Attributes: ``points`` (W, 3), ``arc`` (W,) cumulative arc length [m] (arc[0] = 0), ``length`` [m],
    ``entry`` (3,) the unit direction of the first segment.
    """

    def __init__(self, points, name: str = "path"):
        p = torch.as_tensor(points)
        if not p.is_floating_point() or p.dim() != 2 or p.shape[1] != 3 or p.shape[0] < 2:
            raise ValueError(f"{name}: expected a float (W, 3) polyline with W >= 2 points [m], got {p.dtype} "
                             f"{tuple(p.shape)}")
        p = p.to(F64)
        if not torch.isfinite(p).all():
            raise ValueError(f"{name}: has NaN/inf entries")
        seg = torch.linalg.vector_norm(p[1:] - p[:-1], dim=-1)
        if not bool((seg > 0).all()):
            i = int((seg <= 0).nonzero()[0])
            raise ValueError(f"{name}: points {i} and {i + 1} coincide; expected a polyline without repeated points")
        self.points, self.name = p, name
        self.segment_length = seg
        self.arc = torch.cat([torch.zeros(1, dtype=F64), torch.cumsum(seg, 0)])
        self.length = float(self.arc[-1])
        self.entry = (p[1] - p[0]) / seg[0]

    def at(self, s: Tensor) -> Tensor:
        """Points (..., 3) [m] at arc lengths s (...) [m]: on the polyline for 0 ≤ s ≤ length, on the entry line
        points[0] + s·entry for s < 0, the end point for s > length."""
        s = torch.as_tensor(s, dtype=F64)
        inside = s.clamp(0.0, self.length)
        i = (torch.searchsorted(self.arc, inside.reshape(-1), right=True) - 1).clamp(0, len(self.arc) - 2)
        i = i.reshape(s.shape)
        t = ((inside - self.arc[i]) / self.segment_length[i]).unsqueeze(-1)
        on_path = self.points[i] + t * (self.points[i + 1] - self.points[i])
        before = self.points[0] + s.clamp(max=0.0).unsqueeze(-1) * self.entry
        return torch.where((s < 0).unsqueeze(-1), before, on_path)

    def tangent(self, s: Tensor) -> Tensor:
        """Unit directions (..., 3) of the path at arc lengths s (...) [m]: of the segment holding s, of the entry
        line for s < 0, of the last segment beyond the end."""
        s = torch.as_tensor(s, dtype=F64)
        i = (torch.searchsorted(self.arc, s.clamp(0.0, self.length).reshape(-1), right=True) - 1)
        i = i.clamp(0, len(self.arc) - 2).reshape(s.shape)
        along = (self.points[i + 1] - self.points[i]) / self.segment_length[i].unsqueeze(-1)
        return torch.where((s < 0).unsqueeze(-1), self.entry, along)

    def distance(self, x: Tensor, upto: Tensor, chunk: int = 16) -> Tensor:
        """Distance (T, K) [m] of points x (T, K, 3) to the polyline's part from arc 0 to ``upto`` (T,) [m]
        (the traversed path of each row; ``upto`` ≤ 0 means the entry point alone): the nearest point on any of
        its segments, exactly. The nearest segment is found from squared distances expanded into matrix
        products; the distance to it (and to its neighbours) is then computed directly, to round-off."""
        out = []
        for rows in range(0, x.shape[0], chunk):
            xs, u = x[rows:rows + chunk].to(F64), upto[rows:rows + chunk].to(F64)
            n = max(1, int((self.arc[:-1] < u.max()).sum()))                        # segments any row reaches
            a, d, start = self.points[:n], self.points[1:n + 1] - self.points[:n], self.arc[:n]
            dd = (d * d).sum(-1)
            frac = ((u[:, None] - start) / self.segment_length[:n]).clamp(0.0, 1.0)      # (T, S) truncation
            keep = start < u[:, None]
            keep[:, 0] = True
            xa = xs @ a.T - (a * a).sum(-1) * 0.5                                    # (T, K, S): x·a − |a|²/2
            xd = xs @ d.T - (a * d).sum(-1)                                          # (x − a)·d
            t = torch.minimum((xd / dd).clamp_min(0.0), frac.unsqueeze(1))
            # |x − a − t d|² − |x|² = −2(x·a − |a|²/2) − 2t (x − a)·d + t²|d|²
            gap2 = -2 * xa - 2 * t * xd + t * t * dd
            gap2 = torch.where(keep.unsqueeze(1), gap2, torch.full_like(gap2, float("inf")))
            best = gap2.argmin(-1, keepdim=True)                                     # (T, K, 1)
            near = torch.cat([best - 1, best, best + 1], -1).clamp(0, a.shape[0] - 1)
            ok = keep.unsqueeze(1).expand_as(gap2).gather(-1, near)
            tn = t.gather(-1, near)
            foot = a[near] + tn.unsqueeze(-1) * d[near]                             # (T, K, 3, 3)
            exact = torch.linalg.vector_norm(xs.unsqueeze(2) - foot, dim=-1)
            out.append(torch.where(ok, exact, torch.full_like(exact, float("inf"))).amin(-1))
        return torch.cat(out)

    def project(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The nearest point of the whole polyline to each point x (T, 3): (its arc length (T,) [m], the
        distance (T,) [m])."""
        a, b = self.points[:-1], self.points[1:]
        d = b - a
        rel = x.unsqueeze(1) - a                                                     # (T, S, 3)
        t = ((rel * d).sum(-1) / (d * d).sum(-1)).clamp(0.0, 1.0)
        gap = torch.linalg.vector_norm(rel - t.unsqueeze(-1) * d, dim=-1)
        best = gap.argmin(-1)
        rows = torch.arange(x.shape[0])
        return self.arc[best] + t[rows, best] * self.segment_length[best], gap[rows, best]
