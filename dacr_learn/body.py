"""The body of a continuum robot: points along its backbone, their arc length and the envelope radius.

A segment's body is its backbone swept by a ball of the segment's ``body_radius`` (robot file,
:attr:`~dacr_learn.robot.SegmentSpec.body_radius`; default: the segment's largest joint radius). Every model
that has a body returns a :class:`BodyPoints` with the same layout, P = 1 + m·K points for K points per segment:
the base origin, then per segment k the points at the fractions j/K (j = 1 … K) of the segment's reference
length, so the last point of segment k is its end (and the base of segment k + 1). ``arc_length`` is the
reference (unstretched) arc length of each point from the robot's base [m]; an extending segment's points sit
at the same fractions of its current length β. ``radius`` is the envelope radius of the segment a point belongs
to (the base point: the first segment's). Between two consecutive points the backbone stays within
:func:`chord_sag` of their chord — the bound that collision checks of the swept body (:mod:`dacr_learn.scene`)
subtract.

:func:`cc_body` is the exact constant-curvature body of a robot from its Clarke features
(:func:`~dacr_learn.kinematics.backbone_points`), differentiable in the features.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .kinematics import backbone_points
from .robot import RobotSpec


class BodyPoints(NamedTuple):
    """Points on a robot's body: points (B, P, 3) [m] in the model's base frame (the arm's base frame for an arm
    composite); arc_length (P,) [m] from the continuum robot's base, non-decreasing; radius (P,) [m] the envelope
    radius at each point (the layout of the module docstring)."""

    points: Tensor
    arc_length: Tensor
    radius: Tensor


def check_points_per_segment(points_per_segment: int) -> int:
    """``points_per_segment`` as an int ≥ 1 (ValueError otherwise)."""
    if isinstance(points_per_segment, bool) or not isinstance(points_per_segment, int) or points_per_segment < 1:
        raise ValueError(f"points_per_segment: expected an integer >= 1, got {points_per_segment!r}")
    return points_per_segment


def segment_body_radii(spec: RobotSpec) -> tuple[float, ...]:
    """(m,) envelope radius [m] per segment (the robot file's ``body_radius``)."""
    return tuple(float(s.body_radius) for s in spec.segments)


def body_layout(spec: RobotSpec, points_per_segment: int, dtype: torch.dtype = torch.float64,
                device: torch.device | str | None = None) -> tuple[Tensor, Tensor]:
    """(arc_length (P,), radius (P,)) [m] of the body layout of the module docstring, P = 1 + m·K."""
    k = check_points_per_segment(points_per_segment)
    radii_of_segments = segment_body_radii(spec)
    arcs, radii, start = [0.0], [radii_of_segments[0]], 0.0
    for seg, r in zip(spec.segments, radii_of_segments, strict=True):
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
    """The exact constant-curvature body of feature tensors (..., m, 4) (:func:`~.kinematics.backbone_points`),
    differentiable in the features."""
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


def transform_body(body: BodyPoints, pose: Tensor) -> BodyPoints:
    """The body in another frame: pose (B, 4, 4) of the body's frame in the new one."""
    points = (pose[:, None, :3, :3] @ body.points.unsqueeze(-1)).squeeze(-1) + pose[:, None, :3, 3]
    return BodyPoints(points, body.arc_length, body.radius)


def chord_sag(points: Tensor) -> Tensor:
    """An upper bound (B, P − 1) [m] on how far the backbone between consecutive points (B, P, 3) strays from
    the chord joining them, for points sampled as :class:`BodyPoints` (at least 2 per segment).

    The arc between two samples of one segment spans an angle ψ and strays at most (c/2)·tan(ψ/4) from its chord
    of length c. Within a segment the angle between consecutive chords is ψ; at a segment joint it is at most
    the mean of both segments' ψ; so each chord takes the larger turning angle at its two ends (0 at the body's
    ends), which is at least its own ψ when every segment has two or more chords."""
    chord = points[:, 1:] - points[:, :-1]                                     # (B, P − 1, 3)
    length = torch.linalg.vector_norm(chord, dim=-1)
    unit = chord / length.clamp_min(1e-300).unsqueeze(-1)
    cos = (unit[:, 1:] * unit[:, :-1]).sum(-1).clamp(-1.0, 1.0)
    turn = torch.acos(cos)                                                     # (B, P − 2) at inner points
    pad = torch.zeros_like(turn[:, :1])
    angle = torch.maximum(torch.cat([pad, turn], 1), torch.cat([turn, pad], 1))
    return length / 2 * torch.tan(angle.clamp(max=torch.pi * 0.99) / 4)
