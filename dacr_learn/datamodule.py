"""LightningDataModule serving synthetic datasets as in-memory tensor batches.

``source``: "cc" (constant-curvature samples, :mod:`dacr_learn.data`) or "cosserat" (tension-driven
static shapes of the Cosserat-rod model, :mod:`dacr_learn.data.cosserat`; options in ``cosserat``).

Batches are dicts {"q": (B, num_joints), "pose": (B, 4, 4), "valid": (B,) bool} drawn by
index from tensors held in memory: no per-sample ``__getitem__``, no worker processes. Under
DDP each rank takes a disjoint shard (padded to equal length so every rank runs the same
number of steps; padding rows carry ``valid = False`` and are ignored by the metrics).
"""
from __future__ import annotations

import math
from pathlib import Path

import lightning.pytorch as pl
import torch
from torch import Tensor

from .body import check_points_per_segment, subsample
from .data import SamplerOptions, generate, generate_or_load, with_segment_frames
from .data import cosserat as cosserat_dataset
from .kinematics import backbone_points
from .robot import RobotSpec

BATCH_KEYS = ("q", "pose")
OPTIONAL_BATCH_KEYS = ("segment_frames",)     # served when the dataset holds them
BODY_KEY = "backbone"                         # served only when asked for (``body_points``)


def _rank_world() -> tuple[int, int]:
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class TensorBatches:
    """Iterable of index batches over a dict of equally long tensors (reshuffled every epoch)."""

    def __init__(self, tensors: dict[str, Tensor], batch_size: int, shuffle: bool, seed: int = 0,
                 extra_keys: tuple[str, ...] = ()):
        if batch_size < 1:
            raise ValueError(f"batch_size: expected >= 1, got {batch_size}")
        keys = BATCH_KEYS + OPTIONAL_BATCH_KEYS + tuple(extra_keys)
        self.tensors = {k: tensors[k] for k in keys if k in tensors or k in BATCH_KEYS}
        self.n = self.tensors["q"].shape[0]
        self.batch_size, self.shuffle, self.seed, self.epoch = batch_size, shuffle, seed, 0

    def _shard(self) -> tuple[Tensor, Tensor]:
        rank, world = _rank_world()
        if self.shuffle:
            order = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed + self.epoch))
            self.epoch += 1
        else:
            order = torch.arange(self.n)
        per_rank = math.ceil(self.n / world)
        pad = per_rank * world - self.n
        valid = torch.cat([torch.ones(self.n, dtype=torch.bool), torch.zeros(pad, dtype=torch.bool)])
        order = torch.cat([order, order[:pad]])
        return order[rank::world], valid[rank::world]

    def __iter__(self):
        order, valid = self._shard()
        for i in range(0, len(order), self.batch_size):
            idx = order[i:i + self.batch_size]
            batch = {k: v[idx] for k, v in self.tensors.items()}
            batch["valid"] = valid[i:i + self.batch_size]
            yield batch

    def __len__(self) -> int:
        return math.ceil(math.ceil(self.n / _rank_world()[1]) / self.batch_size)


def _options(spec: RobotSpec, source: str, cosserat: dict | None, sampler: SamplerOptions):
    """The generation options of a source: ``sampler`` for "cc", CosseratOptions for "cosserat"."""
    if source == "cc":
        if cosserat is not None:
            raise ValueError("cosserat: options of the Cosserat source given with source 'cc'; set source: cosserat")
        return sampler
    if source != "cosserat":
        raise ValueError(f"source: expected 'cc' or 'cosserat', got {source!r}")
    if spec.mechanics is None:
        raise ValueError(f"robot {spec.name!r}: source 'cosserat' needs a robot description with a mechanics: "
                         "block (e.g. configs/robots/tdcr_3seg_cosserat.yaml, docs/cosserat.md §1)")
    if sampler != SamplerOptions():
        raise ValueError(f"source 'cosserat': the noise options are not supported, got {sampler}")
    return cosserat_dataset.CosseratOptions.from_dict(cosserat)


class KinematicsDataModule(pl.LightningDataModule):
    """Synthetic dataset of a robot, split into train / val / test.

    Args:
        robot: path of a robot YAML (configs/robots/*.yaml) or a RobotSpec dict.
        n_train, n_val, n_test: split sizes. batch_size: training batch size (eval uses 4×).
        seed: sampling seed (the splits are consecutive slices of one seeded dataset).
        joint_noise, pose_noise_pos, pose_noise_rot, common_offset: see SamplerOptions [m, rad].
        cache_dir: if set, the dataset is written there (tensors.pt + meta.json) and re-used.
        segment_frames: also serve every segment's end frame ("segment_frames", (B, m, 4, 4)) in batches.
        source: "cc" (default) or "cosserat" (needs a robot with a ``mechanics:`` block; no noise options).
        cosserat: options of the Cosserat source (:class:`~dacr_learn.data.cosserat.CosseratOptions`:
            tension_max, tendons_pulled, gravity, tip_force_max, steps_per_segment, tol, max_iter).
        body_points: K > 0 serves the true body in batches ("backbone", (B, 1 + m·K, 3) [m]; docs/body.md,
            "Training the shape output"; with "cosserat", K must divide steps_per_segment).
    """

    def __init__(self, robot: str | dict = "configs/robots/default.yaml", n_train: int = 100_000,
                 n_val: int = 5_000, n_test: int = 10_000, batch_size: int = 1024, seed: int = 0,
                 joint_noise: float = 0.0, pose_noise_pos: float = 0.0, pose_noise_rot: float = 0.0,
                 common_offset: float = 0.0, cache_dir: str | None = None, segment_frames: bool = False,
                 source: str = "cc", cosserat: dict | None = None, body_points: int = 0):
        super().__init__()
        self.spec = RobotSpec.coerce(robot)
        for name, v in (("n_train", n_train), ("n_val", n_val), ("n_test", n_test)):
            if v < 1:
                raise ValueError(f"{name}: expected >= 1 samples, got {v}")
        self.sizes = (n_train, n_val, n_test)
        self.batch_size, self.seed, self.cache_dir = batch_size, seed, cache_dir
        self.segment_frames = segment_frames
        self.body_points = int(body_points) if body_points else 0
        if self.body_points:
            check_points_per_segment(body_points)
        self.source = source
        self.options = _options(self.spec, source, cosserat,
                                SamplerOptions(joint_noise, pose_noise_pos, pose_noise_rot, common_offset))
        self.splits: dict[str, dict[str, Tensor]] = {}

    def _data(self) -> dict[str, Tensor]:
        n, cosserat = sum(self.sizes), self.source == "cosserat"
        if self.cache_dir is not None:
            load = cosserat_dataset.generate_or_load if cosserat else generate_or_load
            return load(Path(self.cache_dir), self.spec, n, self.seed, self.options)
        return (cosserat_dataset.generate if cosserat else generate)(self.spec, n, self.seed, self.options)

    def prepare_data(self) -> None:
        if self.cache_dir is not None:
            self._data()

    def setup(self, stage: str | None = None) -> None:
        if self.splits:
            return
        n = sum(self.sizes)
        data = self._data()
        if self.source == "cosserat":     # the solver's segment frames, served only when asked for
            data = data if self.segment_frames else {k: v for k, v in data.items() if k != "segment_frames"}
        elif self.segment_frames:
            data = with_segment_frames(self.spec, data)
        if self.body_points:
            data = {**data, BODY_KEY: self._body(data)}
        bounds = [0, self.sizes[0], self.sizes[0] + self.sizes[1], n]
        for name, lo, hi in zip(("train", "val", "test"), bounds[:-1], bounds[1:], strict=True):
            self.splits[name] = {k: v[lo:hi] for k, v in data.items()}

    def _body(self, data: dict[str, Tensor]) -> Tensor:
        """The true body (N, 1 + m·K, 3) [m] of the dataset's samples at ``body_points`` K per segment."""
        k = self.body_points
        if self.source == "cc":
            return backbone_points(self.spec, data["features"], k)
        steps = self.options.steps_per_segment
        if steps % k:
            raise ValueError(f"body_points: the Cosserat backbone has {steps} points per segment "
                             f"(data.cosserat.steps_per_segment); expected a divisor of it, got {k}")
        return subsample(data[BODY_KEY], self.spec.num_segments, steps // k)

    def _loader(self, split: str, batch_size: int, shuffle: bool) -> TensorBatches:
        extra = (BODY_KEY,) if self.body_points else ()
        return TensorBatches(self.splits[split], batch_size, shuffle=shuffle, seed=self.seed if shuffle else 0,
                             extra_keys=extra)

    def train_dataloader(self):
        return self._loader("train", self.batch_size, True)

    def val_dataloader(self):
        return self._loader("val", 4 * self.batch_size, False)

    def test_dataloader(self):
        return self._loader("test", 4 * self.batch_size, False)
