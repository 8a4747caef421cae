"""Tendon routing geometry of a tendon-driven robot for the Cosserat-rod model (docs/cosserat.md §1).

Tendon i is joint i of the joint vector (docs/design.md §3). It runs straight at the body-frame offset
r_i = d_i·(cos ψ_i, sin ψ_i, 0) [m] from the base to the distal end of its own segment. With ``routing:
coupled`` it passes the segments before at its own angle, at its own radius (the default, as the Clarke maps)
or, with ``passing="segment"``, at the radius of the segment it passes (the hardware CC model's geometry).
Independent routing of several segments is refused (it would need a model of how distal tendons bypass).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..robot import RobotSpec


@dataclass(frozen=True)
class TendonRouting:
    """Float64 constants of the routing, T tendons, m segments: offsets (T, 3) body-frame r_i [m]; segment (T,) at
    whose distal end tendon i terminates; ends (m + 1,) segment boundaries [m], ends[0] = 0; segment_offsets
    (m, T, 3) offset of tendon i inside segment k where it differs from r_i, else None.
    """

    offsets: Tensor
    segment: Tensor
    ends: Tensor
    segment_offsets: Tensor | None = None

    def offsets_in(self, k: int) -> Tensor:
        """(T, 3) body-frame offsets of every tendon inside segment k [m] (meaningful for the active ones)."""
        if self.segment_offsets is None:
            return self.offsets
        return self.segment_offsets[min(k, self.segment_offsets.shape[0] - 1)]

    @property
    def max_offset(self) -> float:
        """Largest distance of a tendon from the backbone anywhere along it [m]."""
        every = self.offsets if self.segment_offsets is None else self.segment_offsets
        return float(every.norm(dim=-1).max())

    @property
    def num_tendons(self) -> int:
        return self.offsets.shape[0]

    def active(self, k: int) -> Tensor:
        """Indices (long) of the tendons that run along segment k (those terminating at k or beyond)."""
        return torch.nonzero(self.segment >= k).flatten()

    def terminating(self, k: int) -> Tensor:
        """Indices (long) of the tendons that terminate at the distal end of segment k."""
        return torch.nonzero(self.segment == k).flatten()


def tendon_routing(spec: RobotSpec, passing: str = "own") -> TendonRouting:
    """The routing of ``spec`` (types "0"/"I" only; coupled routing or one segment); ``passing``: "own" or
    "segment", the radius of a tendon inside a segment it passes (module docstring)."""
    if passing not in ("own", "segment"):
        raise ValueError(f"passing: got {passing!r}, expected 'own' or 'segment'")
    for j, seg in enumerate(spec.segments):
        if seg.twists:
            raise ValueError(f"segments[{j}].type: got {seg.type!r}, expected a tendon-driven segment of type "
                             '"0" or "I" (twist actuation is not part of the Cosserat-rod model)')
    if spec.num_segments > 1 and spec.routing != "coupled":
        raise ValueError(f"routing: got {spec.routing!r}, expected 'coupled' for a multi-segment robot in the "
                         "Cosserat-rod model (independent routing needs a model of how distal tendons bypass "
                         "the proximal segments)")
    offsets, segment = [], []
    for k, seg in enumerate(spec.segments):
        for psi, d in zip(seg.joint_angles, seg.joint_radii, strict=True):
            psi_t = torch.tensor(psi, dtype=torch.float64)
            offsets.append(torch.stack([d * torch.cos(psi_t), d * torch.sin(psi_t), psi_t.new_zeros(())]))
            segment.append(k)
    lengths = torch.tensor([0.0] + [s.length for s in spec.segments], dtype=torch.float64)
    offsets = torch.stack(offsets)
    per_segment = None
    if passing == "segment":
        direction = offsets / offsets.norm(dim=-1, keepdim=True)
        per_segment = torch.stack([direction * seg.radius for seg in spec.segments])
        own = torch.tensor(segment)
        per_segment[own, torch.arange(len(segment))] = offsets        # inside its own segment: its own offset
    return TendonRouting(offsets, torch.tensor(segment), torch.cumsum(lengths, 0), per_segment)
