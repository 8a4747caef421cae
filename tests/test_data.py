"""Synthetic data: sampling distribution, determinism, dataset files and checksum refusal; broken dataset files
(truncated tensors.pt, broken meta.json) give a ValueError naming the file."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import TDCR3, TYPE1, names, truncated

from dacr_learn import data as ddata
from dacr_learn.data import SamplerOptions, bending_subsets, generate, load_dataset, sample_features, save_dataset
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec

TYPE3 = RobotSpec.from_yaml("configs/robots/type3.yaml")
COUPLED = RobotSpec.from_yaml("configs/robots/tdcr_3seg_coupled.yaml")
pytestmark = pytest.mark.usefixtures("one_thread")


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


# --------------------------------------------------------------------------------------------------
# Combination regimes (max_bending) and segment frames
# --------------------------------------------------------------------------------------------------


def test_bending_subsets():
    masks = bending_subsets(3, 2)
    assert masks.shape == (7, 3) and set(map(tuple, masks.tolist())) == {
        (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1)}
    with pytest.raises(ValueError, match="max_bending"):
        bending_subsets(3, 4)


def test_generate_with_max_bending_and_segment_frames():
    data = generate(TDCR3, 2000, seed=7, max_bending=2, segment_frames=True)
    bending = data["features"][..., :2].abs().sum(-1) > 0                       # (N, m)
    assert int(bending.sum(-1).max()) == 2
    assert len({tuple(b) for b in bending.tolist()}) == 7                        # every subset occurs
    assert bool((data["features"][..., 2] > 0).all())                           # β still sampled
    assert torch.allclose(data["segment_frames"][:, -1], data["pose_clean"], rtol=0, atol=1e-6)
    assert torch.equal(generate(TDCR3, 50, seed=7)["q"], generate(TDCR3, 50, seed=7, segment_frames=True)["q"])


# --------------------------------------------------------------------------------------------------
# Broken dataset files
# --------------------------------------------------------------------------------------------------


@pytest.fixture()
def dataset(tmp_path) -> tuple[Path, RobotSpec]:
    spec = RobotSpec.from_yaml(TYPE1)
    return ddata.save_dataset(tmp_path / "ds", spec, ddata.generate(spec, 16, seed=0), 0, ddata.SamplerOptions()), spec


@pytest.mark.parametrize("keep", [0, 1, 100, 0.5, -100, -10, -1])
def test_truncated_tensor_file(dataset, keep):
    """Truncations at every depth: torch raises EOFError, UnpicklingError, RuntimeError or OSError (EINVAL)."""
    directory, spec = dataset
    path = directory / ddata.TENSOR_FILE
    truncated(path, int(keep * path.stat().st_size) if isinstance(keep, float) else keep)
    with pytest.raises(ValueError, match=names(path, "expected the tensors.pt of a dataset", "found a file of",
                                               "not a complete torch.save archive")) as err:
        ddata.load_dataset(directory, spec)
    assert err.value.__cause__ is not None


def test_tensor_file_of_another_content(dataset):
    directory, spec = dataset
    path = directory / ddata.TENSOR_FILE
    torch.save([1, 2], path)
    with pytest.raises(ValueError, match=names(path, "a dict of named tensors", "found a list")):
        ddata.load_dataset(directory, spec)
    torch.save({"q": torch.zeros(2), "note": "text"}, path)
    with pytest.raises(ValueError, match=names(path, "not named tensors", "'note': 'str'")):
        ddata.load_dataset(directory, spec)


@pytest.mark.parametrize("text,found", [("{not json", "found invalid JSON"), ("[1, 2]", "found a JSON list"),
                                        ("", "found invalid JSON")])
def test_broken_meta_json(dataset, text, found):
    directory, spec = dataset
    path = directory / ddata.META_FILE
    path.write_text(text)
    with pytest.raises(ValueError, match=names(path, "expected the meta.json of a dataset", found)):
        ddata.load_dataset(directory, spec)
    with pytest.raises(ValueError, match=names(path, found)):       # a cache directory is not silently replaced
        ddata.generate_or_load(directory, spec, 16, 0)


def test_meta_json_with_a_bad_robot(dataset):
    directory, spec = dataset
    path = directory / ddata.META_FILE
    meta = json.loads(path.read_text())
    meta["robot"] = {"segments": "none"}
    path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=names(path, "segments: got 'none'")):
        ddata.load_dataset(directory, spec)
