"""Synthetic data: sampling distribution, determinism, dataset files and checksum refusal, batching."""
import json
import math

import pytest
import torch

from dacr_learn.data import SamplerOptions, generate, load_dataset, sample_features, save_dataset
from dacr_learn.datamodule import KinematicsDataModule, TensorBatches
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec

TYPE3 = RobotSpec.from_yaml("configs/robots/type3.yaml")
COUPLED = RobotSpec.from_yaml("configs/robots/tdcr_3seg_coupled.yaml")


def test_generation_is_bit_identical_for_a_seed_and_differs_across_seeds():
    opts = SamplerOptions(joint_noise=1e-4, pose_noise_pos=1e-4, pose_noise_rot=1e-3, common_offset=2e-3)
    a, b, c = generate(TYPE3, 500, 7, opts), generate(TYPE3, 500, 7, opts), generate(TYPE3, 500, 8, opts)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert not torch.equal(a["q"], c["q"])


def test_samples_respect_limits_and_are_uniform_in_area_over_the_bending_disk():
    g = torch.Generator().manual_seed(0)
    f = sample_features(TYPE3, 200_000, g, torch.float64)
    seg = TYPE3.segments[0]
    phi = torch.linalg.vector_norm(f[:, 0, :2], dim=-1) / seg.radius
    assert phi.max() <= seg.bend + 1e-12
    # uniform in area: P(φ ≤ b/2) = 1/4, and θ uniform (mean of cos θ ≈ 0)
    assert abs((phi <= seg.bend / 2).double().mean().item() - 0.25) < 0.005
    theta = torch.atan2(f[:, 0, 1], f[:, 0, 0])
    assert abs(torch.cos(theta).mean().item()) < 0.01
    lo, hi = seg.length_range
    assert f[:, 0, 2].min() >= lo and f[:, 0, 2].max() <= hi
    tlo, thi = seg.twist_range
    assert f[:, 0, 3].min() >= tlo and f[:, 0, 3].max() <= thi


def test_clean_samples_are_consistent_with_encoder_and_kinematics():
    d = generate(COUPLED, 300, 0, dtype=torch.float64)
    assert torch.allclose(ClarkeEncoder(COUPLED)(d["q"]), d["features"], atol=1e-12)
    assert torch.allclose(forward_kinematics(COUPLED, d["features"]), d["pose"], atol=1e-12)


def test_noise_options_change_only_what_they_should():
    clean = generate(TYPE3, 200, 3)
    drift = generate(TYPE3, 200, 3, SamplerOptions(common_offset=1e-3))
    nl = TYPE3.num_length_joints
    assert torch.allclose(drift["q"][:, :nl] - clean["q"][:, :nl], torch.full((200, nl), 1e-3), atol=1e-7)
    assert torch.equal(drift["q"][:, nl:], clean["q"][:, nl:])          # twist is not a length
    assert torch.equal(drift["pose"], clean["pose"])
    rot = generate(TYPE3, 200, 3, SamplerOptions(pose_noise_rot=1e-2))["pose"][:, :3, :3]
    eye = torch.eye(3).expand(200, 3, 3)
    assert torch.allclose(rot.mT @ rot, eye, atol=1e-5)                 # noisy rotations stay rotations
    with pytest.raises(ValueError, match="joint_noise"):
        SamplerOptions(joint_noise=-1.0)


def test_dataset_round_trip_and_refusals(tmp_path):
    opts = SamplerOptions(joint_noise=1e-4)
    d = generate(TYPE3, 100, 1, opts)
    save_dataset(tmp_path / "ds", TYPE3, d, 1, opts)
    meta = json.loads((tmp_path / "ds" / "meta.json").read_text())
    assert meta["seed"] == 1 and meta["options"]["joint_noise"] == 1e-4 and len(meta["sha256"]) == 64
    back, _ = load_dataset(tmp_path / "ds", TYPE3)
    assert all(torch.equal(back[k], d[k]) for k in d)
    with pytest.raises(ValueError, match="robot spec mismatch"):
        load_dataset(tmp_path / "ds", COUPLED)
    d["q"][0, 0] += 1e-6                                                  # tamper with the tensors
    torch.save(d, tmp_path / "ds" / "tensors.pt")
    with pytest.raises(ValueError, match="checksum mismatch"):
        load_dataset(tmp_path / "ds", TYPE3)
    with pytest.raises(ValueError, match="missing"):
        load_dataset(tmp_path / "nothing")


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
