"""The body of a continuum robot: points along its backbone, their arc length and the envelope radius.

Every model that has a body returns a :class:`BodyPoints` with the same layout, P = 1 + m·K points for K points
per segment: the base origin, then per segment k the points at the fractions j/K (j = 1 … K) of the segment's
reference length, so the last point of segment k is its end (and the base of segment k + 1). ``arc_length`` is
the reference (unstretched) arc length of each point from the robot's base [m]; an extending segment's points
sit at the same fractions of its current length β. ``radius`` is the envelope radius of the segment a point
belongs to (the base point: the first segment's): the robot file's ``body_radius`` where a segment has one,
else the largest joint radius of the segment (the tendons' circle: the disks that guide them are at least
that wide).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .kinematics import backbone_points
from .robot import RobotSpec


class BodyPoints(NamedTuple):
    """points (B, P, 3) [m] in the model's base frame; arc_length (P,) [m] from the robot's base, non-decreasing;
    radius (P,) [m] envelope radius at each point."""

    points: Tensor
    arc_length: Tensor
    radius: Tensor


def check_points_per_segment(points_per_segment: int) -> int:
    """``points_per_segment`` as an int ≥ 1 (ValueError otherwise)."""
    if isinstance(points_per_segment, bool) or not isinstance(points_per_segment, int) or points_per_segment < 1:
        raise ValueError(f"points_per_segment: expected an integer >= 1, got {points_per_segment!r}")
    return points_per_segment


def segment_body_radii(spec: RobotSpec) -> tuple[float, ...]:
    """(m,) envelope radius [m] per segment: ``body_radius`` where the segment has one, else its largest joint
    radius."""
    return tuple(float(getattr(s, "body_radius", None) or max(s.joint_radii)) for s in spec.segments)


def body_layout(spec: RobotSpec, points_per_segment: int, dtype: torch.dtype = torch.float64,
                device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """(arc_length (P,), radius (P,)) [m] of the body layout of the module docstring, P = 1 + m·K."""
    k = check_points_per_segment(points_per_segment)
    arcs, radii, start = [0.0], [segment_body_radii(spec)[0]], 0.0
    for seg, r in zip(spec.segments, segment_body_radii(spec), strict=True):
        arcs += [start + seg.length * j / k for j in range(1, k + 1)]
        radii += [r] * k
        start += seg.length
    return (torch.tensor(arcs, dtype=dtype, device=device), torch.tensor(radii, dtype=dtype, device=device))


def body_of_points(spec: RobotSpec, points: Tensor, points_per_segment: int) -> BodyPoints:
    """Points (..., 1 + m·K, 3) [m] of the layout → BodyPoints with the layout's arc lengths and radii
    (ValueError for another number of points)."""
    k = check_points_per_segment(points_per_segment)
    expected = 1 + spec.num_segments * k
    if points.dim() < 2 or points.shape[-2:] != (expected, 3):
        raise ValueError(f"points: expected (..., {expected}, 3) (1 + {spec.num_segments} segments x {k} points), "
                         f"got {tuple(points.shape)}")
    return BodyPoints(points, *body_layout(spec, k, points.dtype, points.device))


def cc_body(spec: RobotSpec, features: Tensor, points_per_segment: int = 16) -> BodyPoints:
    """The exact constant-curvature body of feature tensors (..., m, 4) (:func:`~.kinematics.backbone_points`)."""
    k = check_points_per_segment(points_per_segment)
    return body_of_points(spec, backbone_points(spec, features, k), k)


def subsample(points: Tensor, num_segments: int, stride: int) -> Tensor:
    """Points (..., 1 + m·K, 3) of the layout → every ``stride``-th point of each segment (..., 1 + m·K/stride, 3)
    (K a multiple of ``stride``): e.g. a dataset's backbone on a coarser layout."""
    n = points.shape[-2] - 1
    if stride < 1 or n % num_segments or (n // num_segments) % stride:
        raise ValueError(f"stride: expected a divisor of the {n // max(num_segments, 1)} points per segment, "
                         f"got {stride}")
    return torch.cat([points[..., :1, :], points[..., 1:, :][..., stride - 1::stride, :]], dim=-2)
