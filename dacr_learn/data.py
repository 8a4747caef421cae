"""Synthetic constant-curvature datasets: sampling, dataset files, batching.

Sampling (per segment, from the robot's limits): the bending vector u = φ·(cos θ, sin θ) is
uniform in area over the disk φ ≤ bend (φ = bend·√U₁, θ = 2πU₂), ρ = d·u; β and α are
uniform in their ranges. Joint vectors come from :class:`ClarkeDecoder`, tip poses from
:func:`forward_kinematics`. Generation is deterministic for a seed (a private generator).

Tensors of a dataset (all in SI units):
  q (N, num_joints) [m, rad] — measured joint vector (after noise and common-mode offset),
  q_clean (N, num_joints) — noise-free joint vector, features (N, m, 4) — sampled features,
  pose (N, 4, 4) — measured tip pose (after pose noise), pose_clean (N, 4, 4),
  optional segment_frames (N, m, 4, 4) — noise-free pose of every segment's end in the base frame.

Combination regimes (``max_bending``): each sample bends only a subset of at most ``max_bending``
segments, drawn uniformly among all such subsets (the empty one included); the others are
straight (ρ = 0), their β and α still sampled. ``None`` (default) bends every segment.
"""
from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from .checks import load_torch_file, read_json_object
from .kinematics import forward_kinematics, segment_tip_poses
from .layers import ClarkeDecoder
from .robot import RobotSpec

TENSOR_FILE, META_FILE = "tensors.pt", "meta.json"


@dataclass(frozen=True)
class SamplerOptions:
    """Noise model of a synthetic dataset (SI units, standard deviations unless noted).

    joint_noise [m]: Gaussian noise on every joint length; pose_noise_pos [m]: on each tip
    coordinate; pose_noise_rot [rad]: rotation by a random axis-angle vector with this std per
    component; common_offset [m]: the same constant added to every joint length (drift).
    """

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
    """Generate n samples (see module docstring for the tensors). Bit-identical for a seed.

    ``segment_frames``: also return the per-segment end frames; ``max_bending``: see the module docstring.
    """
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


def tensors_sha256(tensors: dict[str, Tensor]) -> str:
    """sha256 over the names, dtypes, shapes and raw bytes of the tensors, in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def options_record(options: Any) -> dict:
    """The options dataclass as meta.json stores it (JSON types: tuples become lists)."""
    return json.loads(json.dumps(asdict(options)))


def save_dataset(directory: str | Path, spec: RobotSpec, tensors: dict[str, Tensor], seed: int,
                 options: Any) -> Path:
    """Write ``tensors.pt`` + ``meta.json`` (spec, source, options, seed, sha256) to ``directory``.

    ``options``: the dataclass the tensors were generated with (:class:`SamplerOptions`, or
    ``cosserat.dataset.CosseratOptions``); its ``source`` ("cc", "cosserat") is recorded too."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    meta = {"robot": spec.to_dict(), "source": options.source, "options": options_record(options), "seed": int(seed),
            "num_samples": int(next(iter(tensors.values())).shape[0]), "sha256": tensors_sha256(tensors)}
    tmp = directory / (TENSOR_FILE + ".tmp")
    torch.save(tensors, tmp)
    tmp.replace(directory / TENSOR_FILE)                      # atomic: never a half-written file
    (directory / META_FILE).write_text(json.dumps(meta, indent=2))
    return directory


def _read_meta(directory: Path) -> dict:
    """meta.json of a dataset as a dict (ValueError naming the file when it is not a JSON object)."""
    return read_json_object(directory / META_FILE, f"the {META_FILE} of a dataset written by save_dataset")


def _read_tensors(directory: Path) -> dict[str, Tensor]:
    """tensors.pt of a dataset: a dict of named tensors (ValueError naming the file otherwise)."""
    path = directory / TENSOR_FILE
    expected = f"the {TENSOR_FILE} of a dataset written by save_dataset (a dict of named tensors)"
    tensors = load_torch_file(path, expected)
    if not isinstance(tensors, dict):
        raise ValueError(f"{path}: expected {expected}, found a {type(tensors).__name__}")
    bad = {str(k): type(v).__name__ for k, v in tensors.items() if not (isinstance(k, str) and isinstance(v, Tensor))}
    if bad:
        raise ValueError(f"{path}: expected {expected}, found entries that are not named tensors: {bad}")
    return tensors


def load_dataset(directory: str | Path, spec: RobotSpec | None = None) -> tuple[dict[str, Tensor], dict]:
    """Read a dataset written by :func:`save_dataset`; refuse a checksum or robot-spec mismatch.

    Every refusal is a ValueError naming the directory or file (unreadable, truncated, modified,
    generated for another robot).
    """
    directory = Path(directory)
    for f in (TENSOR_FILE, META_FILE):
        if not (directory / f).is_file():
            raise ValueError(f"dataset {directory}: missing {f}")
    meta, tensors = _read_meta(directory), _read_tensors(directory)
    digest = tensors_sha256(tensors)
    if digest != meta.get("sha256"):
        raise ValueError(f"dataset {directory}: checksum mismatch (meta.json says {meta.get('sha256')}, "
                         f"the tensors hash to {digest}); the file was modified or truncated")
    if spec is not None and _saved_spec(directory, meta) != spec:
        raise ValueError(f"dataset {directory}: robot spec mismatch: the dataset was generated for "
                         f"{meta['robot']['name']!r} ({meta['robot']}), expected {spec.to_dict()}")
    return tensors, meta


def _saved_spec(directory: Path, meta: dict) -> RobotSpec:
    try:
        return RobotSpec.from_dict(meta.get("robot"))
    except ValueError as err:
        raise ValueError(f"{directory / META_FILE}: {err}") from err


def generate_or_load(directory: str | Path, spec: RobotSpec, n: int, seed: int,
                     options: Any = SamplerOptions(),
                     make: Callable[[RobotSpec, int, int, Any], dict[str, Tensor]] | None = None) -> dict[str, Tensor]:
    """Load ``directory`` if it holds exactly this dataset (spec, n, seed, source, options), else generate
    it with ``make(spec, n, seed, options)`` (default :func:`generate`) and save it. A dataset written
    before sources existed (no ``source`` in meta.json) counts as "cc"."""
    directory = Path(directory)
    if (directory / META_FILE).is_file():
        meta = _read_meta(directory)
        if ((meta.get("seed"), meta.get("num_samples"), meta.get("source", "cc"), meta.get("options"))
                == (seed, n, options.source, options_record(options))):
            return load_dataset(directory, spec)[0]
    tensors = (make or generate)(spec, n, seed, options)
    save_dataset(directory, spec, tensors, seed, options)
    return tensors
