"""The follow-the-leader figures of a plan: tip error and shape deviation per step.

At a step whose tip is at arc length s along the path, the **inserted body** is the last min(s, ℓ) of the
backbone (ℓ the backbone's length at that step), measured from the tip back by arc length. It is resampled at
:data:`SAMPLES` points evenly spaced in arc length (linear interpolation between the backbone points), and the
**shape deviation** is the mean and the max of their distances to the traversed path P[0 … s] (exact
point-to-polyline distances). The **tip error** is the tip's distance to the path point at s. All in metres;
divide by the robot's length for the relative figures. The same code scores any planner's output given as
backbone points.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import F64
from .path import Path

SAMPLES = 64   # points of the resampled inserted body


def resample(points: Tensor, arc: Tensor, start: Tensor, end: Tensor, samples: int = SAMPLES) -> Tensor:
    """Points (T, K, 3) [m] at K arc lengths evenly spaced from ``start`` to ``end`` (T,) [m] along polylines
    ``points`` (T, P, 3) whose vertices lie at arc lengths ``arc`` (T, P) or (P,) [m] (non-decreasing)."""
    if samples < 2:
        raise ValueError(f"samples: expected >= 2, got {samples}")
    arc = arc.to(F64).expand(points.shape[:2]).contiguous()
    frac = torch.linspace(0.0, 1.0, samples, dtype=F64)
    want = start.unsqueeze(-1) + frac * (end - start).unsqueeze(-1)                    # (T, K)
    i = (torch.searchsorted(arc, want.contiguous(), right=True) - 1).clamp(0, arc.shape[1] - 2)
    a0, a1 = arc.gather(1, i), arc.gather(1, i + 1)
    t = ((want - a0) / (a1 - a0).clamp_min(1e-300)).clamp(0.0, 1.0).unsqueeze(-1)
    gather = lambda j: points.gather(1, j.unsqueeze(-1).expand(-1, -1, 3))  # noqa: E731
    return gather(i) + t * (gather(i + 1) - gather(i))


def shape_deviation(points: Tensor, arc: Tensor, path: Path, s: Tensor,
                    samples: int = SAMPLES) -> tuple[Tensor, Tensor]:
    """Mean and max distance (T,), (T,) [m] of the inserted body to the traversed path (module docstring).

    points (T, P, 3) [m]: the backbone from base to tip in the path's frame; arc (T, P) or (P,) [m]: their arc
    lengths from the base; s (T,) [m]: the tip's arc length along the path. A step with nothing inserted
    (s ≤ 0) scores 0."""
    points, s = points.to(F64), torch.as_tensor(s, dtype=F64)
    if points.dim() != 3 or points.shape[-1] != 3 or s.shape != points.shape[:1]:
        raise ValueError(f"shape_deviation: expected points (T, P, 3) and s (T,), got {tuple(points.shape)} and "
                         f"{tuple(s.shape)}")
    arc = arc.to(F64).expand(points.shape[:2])
    tip_arc = arc[:, -1]
    inserted = torch.minimum(s.clamp_min(0.0), tip_arc - arc[:, 0])
    body = resample(points, arc, tip_arc - inserted, tip_arc, samples)
    gap = path.distance(body, s)
    none = inserted <= 0
    zero = torch.zeros_like(s)
    return torch.where(none, zero, gap.mean(-1)), torch.where(none, zero, gap.amax(-1))


def tip_error(tip: Tensor, path: Path, s: Tensor) -> Tensor:
    """Distance (T,) [m] of tips (T, 3) [m] to the path points at arc lengths s (T,) [m]."""
    return torch.linalg.vector_norm(tip.to(F64) - path.at(torch.as_tensor(s, dtype=F64)), dim=-1)
