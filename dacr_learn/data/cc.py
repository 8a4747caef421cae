"""Synthetic constant-curvature datasets: sampling of features, joint vectors and tip poses (files: :mod:`.store`).

Per segment the bending vector u = φ·(cos θ, sin θ) is uniform in area over the disk φ ≤ bend (φ = bend·√U₁,
θ = 2πU₂), ρ = d·u; β and α are uniform in their ranges. Joint vectors come from :class:`ClarkeDecoder`, tip
poses from :func:`forward_kinematics`; deterministic for a seed (a private generator). With ``max_bending``
each sample bends a uniformly drawn subset of at most that many segments (the empty one included; the others
straight, ρ = 0, their β and α still sampled); ``None`` bends every segment.

Tensors (SI units): q (N, num_joints) [m, rad] the measured joint vector (after noise and common-mode offset),
q_clean (N, num_joints), features (N, m, 4), pose (N, 4, 4) the measured tip pose (after pose noise),
pose_clean (N, 4, 4), optional segment_frames (N, m, 4, 4): the noise-free end of every segment, base frame.
"""
from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass
from typing import ClassVar

import torch
from torch import Tensor

from ..kinematics import forward_kinematics, segment_tip_poses
from ..layers import ClarkeDecoder
from ..robot import RobotSpec


@dataclass(frozen=True)
class SamplerOptions:
    """Noise model of a synthetic dataset (SI units, standard deviations): joint_noise [m] on every joint length;
    pose_noise_pos [m] on each tip coordinate; pose_noise_rot [rad] per component of a random axis-angle rotation;
    common_offset [m]: one constant added to every joint length (drift)."""

    source: ClassVar[str] = "cc"     # recorded in meta.json (the Cosserat options say "cosserat")
    joint_noise: float = 0.0
    pose_noise_pos: float = 0.0
    pose_noise_rot: float = 0.0
    common_offset: float = 0.0

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not isinstance(v, (int, float)) or v != v or (k != "common_offset" and v < 0):
                raise ValueError(f"{k}: expected a finite number" + (" >= 0" if k != "common_offset" else "")
                                 + f", got {v!r}")


def bending_subsets(num_segments: int, max_bending: int) -> Tensor:
    """(S, m) 0/1 masks of every subset of at most ``max_bending`` of the m segments (empty one first)."""
    if not 0 <= max_bending <= num_segments:
        raise ValueError(f"max_bending: expected 0 … {num_segments} (the number of segments), got {max_bending}")
    masks = [[float(k in c) for k in range(num_segments)]
             for size in range(max_bending + 1) for c in itertools.combinations(range(num_segments), size)]
    return torch.tensor(masks)


def sample_features(spec: RobotSpec, n: int, generator: torch.Generator, dtype=torch.float32,
                    max_bending: int | None = None) -> Tensor:
    """n feature tensors (n, m, 4) uniform over the robot's limits (see module docstring); with
    ``max_bending`` only a random subset of at most that many segments bends in each sample."""
    if n < 1:
        raise ValueError(f"n: expected a positive number of samples, got {n}")
    cols = []
    for seg in spec.segments:
        u = torch.rand(n, 4, generator=generator, dtype=dtype)
        phi, theta = seg.bend * torch.sqrt(u[:, 0]), 2 * torch.pi * u[:, 1]
        lo, hi = seg.length_range or (seg.length, seg.length)
        tlo, thi = seg.twist_range or (0.0, 0.0)
        cols.append(torch.stack([seg.radius * phi * torch.cos(theta), seg.radius * phi * torch.sin(theta),
                                 lo + (hi - lo) * u[:, 2], tlo + (thi - tlo) * u[:, 3]], dim=-1))
    features = torch.stack(cols, dim=1)
    if max_bending is not None:
        masks = bending_subsets(spec.num_segments, max_bending).to(dtype)
        bends = masks[torch.randint(len(masks), (n,), generator=generator)]
        features = torch.cat([features[..., :2] * bends.unsqueeze(-1), features[..., 2:]], dim=-1)
    return features


def _rotation_noise(n: int, std: float, generator: torch.Generator, dtype) -> Tensor:
    from pytorch_kinematics.transforms import so3_exp_map

    return so3_exp_map(std * torch.randn(n, 3, generator=generator, dtype=dtype))


def generate(spec: RobotSpec, n: int, seed: int, options: SamplerOptions = SamplerOptions(),
             dtype=torch.float32, *, segment_frames: bool = False, max_bending: int | None = None) -> dict[str, Tensor]:
    """Generate n samples (tensors of the module docstring), bit-identical for a seed; ``segment_frames``: with the
    per-segment end frames; ``max_bending``: see the module docstring."""
    g = torch.Generator().manual_seed(int(seed))
    features = sample_features(spec, n, g, dtype, max_bending)
    q_clean = ClarkeDecoder(spec)(features)
    pose_clean = forward_kinematics(spec, features)
    q = q_clean.clone()
    nl = spec.num_length_joints
    if options.joint_noise:
        q[:, :nl] += options.joint_noise * torch.randn(n, nl, generator=g, dtype=dtype)
    q[:, :nl] += options.common_offset
    pose = pose_clean.clone()
    if options.pose_noise_pos:
        pose[:, :3, 3] += options.pose_noise_pos * torch.randn(n, 3, generator=g, dtype=dtype)
    if options.pose_noise_rot:
        pose[:, :3, :3] = pose[:, :3, :3] @ _rotation_noise(n, options.pose_noise_rot, g, dtype)
    out = {"q": q, "q_clean": q_clean, "features": features, "pose": pose, "pose_clean": pose_clean}
    return with_segment_frames(spec, out) if segment_frames else out


def with_segment_frames(spec: RobotSpec, tensors: dict[str, Tensor]) -> dict[str, Tensor]:
    """``tensors`` plus ``segment_frames`` (N, m, 4, 4): the noise-free end frame of every segment in
    the base frame, from the dataset's ``features`` (the last one is ``pose_clean``)."""
    return {**tensors, "segment_frames": segment_tip_poses(spec, tensors["features"])}
