"""The body of a continuum robot: points along its backbone, their arc length and the envelope radius.

A segment's body is its backbone swept by a ball of the segment's ``body_radius`` (robot file,
:attr:`~dacr_learn.robot.SegmentSpec.body_radius`). :class:`BodyPoints` samples it: P = 1 + m·K points (the
base origin, then K points per segment at equal arc-length steps), the nominal arc length of each and the
radius of the segment each point ends. Between two consecutive points the backbone is an arc of one segment,
and the chord between them stays within :func:`chord_sag` of it — the bound that collision checks of the
swept body (:mod:`dacr_learn.scene`) subtract.

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
    """Points on a robot's body.

    points (B, P, 3) [m] in the model's base frame (the arm's base frame for an arm composite); arc_length (P,)
    [m] from the continuum robot's base, non-decreasing (nominal segment lengths: the point j/K along segment k
    sits at that fraction of the segment's actual length β); radius (P,) [m] the envelope radius at each point
    (the robot file's per-segment ``body_radius``; the base point takes the first segment's)."""

    points: Tensor
    arc_length: Tensor
    radius: Tensor


def body_profile(spec: RobotSpec, points_per_segment: int, dtype: torch.dtype = torch.float64,
                 device: torch.device | None = None) -> tuple[Tensor, Tensor]:
    """(arc_length (P,), radius (P,)) [m] of the 1 + m·K points of :func:`cc_body` (``points_per_segment`` K)."""
    if points_per_segment < 1:
        raise ValueError(f"points_per_segment: expected >= 1, got {points_per_segment}")
    frac = torch.arange(1, points_per_segment + 1, dtype=dtype, device=device) / points_per_segment
    arcs, radii, start = [torch.zeros(1, dtype=dtype, device=device)], [], 0.0
    for seg in spec.segments:
        arcs.append(start + seg.length * frac)
        radii.append(torch.full((points_per_segment,), seg.body_radius, dtype=dtype, device=device))
        start += seg.length
    radii.insert(0, radii[0][:1])
    return torch.cat(arcs), torch.cat(radii)


def cc_body(spec: RobotSpec, features: Tensor, points_per_segment: int = 16) -> BodyPoints:
    """The constant-curvature body of a robot: Clarke features (B, m, 4) → :class:`BodyPoints` with points
    (B, 1 + m·K, 3) [m] in the robot's base frame (exact points on the arcs, differentiable in the features)."""
    points = backbone_points(spec, features, points_per_segment)
    arc, radius = body_profile(spec, points_per_segment, features.dtype, features.device)
    return BodyPoints(points, arc, radius)


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
