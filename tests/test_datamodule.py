"""KinematicsDataModule and its batches: every sample once per epoch, disjoint splits, the dataset cache."""
from __future__ import annotations

import math

import pytest
import torch

from dacr_learn.data import generate
from dacr_learn.datamodule import KinematicsDataModule, TensorBatches


def test_tensor_batches_cover_every_sample_once_per_epoch_and_reshuffle():
    n = 1000
    data = {"q": torch.arange(n, dtype=torch.float32)[:, None], "pose": torch.zeros(n, 4, 4)}
    loader = TensorBatches(data, 128, shuffle=True, seed=0)
    first = torch.cat([b["q"][:, 0] for b in loader])
    second = torch.cat([b["q"][:, 0] for b in loader])
    assert len(loader) == math.ceil(n / 128)
    assert torch.equal(first.sort().values, data["q"][:, 0]) and torch.equal(second.sort().values, data["q"][:, 0])
    assert not torch.equal(first, second)
    assert all(b["valid"].all() for b in loader)


def test_datamodule_splits_are_disjoint_slices(tmp_path):
    dm = KinematicsDataModule("configs/robots/type1.yaml", n_train=300, n_val=50, n_test=70, seed=2,
                              cache_dir=str(tmp_path / "cache"))
    dm.prepare_data()
    dm.setup("fit")
    assert [len(dm.splits[s]["q"]) for s in ("train", "val", "test")] == [300, 50, 70]
    full = generate(dm.spec, 420, 2)
    assert torch.equal(dm.splits["test"]["q"], full["q"][350:])
    assert (tmp_path / "cache" / "meta.json").is_file()
    with pytest.raises(ValueError, match="n_val"):
        KinematicsDataModule("configs/robots/type1.yaml", n_val=0)
