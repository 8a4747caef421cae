"""Cosserat datasets (dacr_learn.data.cosserat): determinism, cache, refusals, the datamodule and train.py
serving them, and the zero-gravity, rigid-tendon limit against the CC model of the same joint lengths."""
import json

import pytest
import torch
from conftest import ROOT, write_run_config

import train
from dacr_learn.cosserat import ConvergenceError
from dacr_learn.data import META_FILE, TENSOR_FILE, SamplerOptions, load_dataset
from dacr_learn.data import cosserat as cd
from dacr_learn.data import generate_or_load as cc_generate_or_load
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec

ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_cosserat.yaml"
FAST = cd.CosseratOptions(steps_per_segment=4)


@pytest.fixture(scope="module")
def spec():
    return RobotSpec.from_yaml(ROBOT)


def test_generation_is_deterministic_for_a_seed_and_has_the_documented_tensors(spec):
    a = cd.generate(spec, 12, seed=3, options=FAST, progress=False, chunk=5)
    b = cd.generate(spec, 12, seed=3, options=FAST, progress=False, chunk=5)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    whole = cd.generate(spec, 12, seed=3, options=FAST, progress=False)    # other chunks: the same up to rounding
    assert torch.allclose(whole["pose"], a["pose"], atol=1e-6) and torch.allclose(whole["q"], a["q"], atol=1e-7)
    c = cd.generate(spec, 12, seed=4, options=FAST, progress=False)
    assert not torch.equal(a["q"], c["q"])
    shapes = {k: tuple(v.shape) for k, v in a.items()}
    assert shapes == {"q": (12, 12), "q_clean": (12, 12), "pose": (12, 4, 4), "pose_clean": (12, 4, 4),
                      "segment_frames": (12, 3, 4, 4), "backbone": (12, 13, 3), "residual": (12,),
                      "tension": (12, 12), "features": (12, 3, 4)}
    assert torch.equal(a["segment_frames"][:, -1], a["pose"])
    assert float(a["residual"].max()) <= FAST.tol
    pulled = (a["tension"] > 0).unflatten(-1, (3, 4)).sum(-1)
    assert bool((pulled <= FAST.tendons_pulled).all()) and float(a["tension"].max()) <= FAST.tension_max
    loaded = cd.generate(spec, 4, seed=3, options=cd.CosseratOptions(steps_per_segment=4, tip_force_max=0.05),
                         progress=False)
    assert float(loaded["tip_force"].norm(dim=-1).max()) <= 0.05 and not torch.equal(loaded["pose"], a["pose"][:4])


def test_cache_is_reused_and_regenerated_when_an_option_changes(spec, tmp_path, monkeypatch):
    first = cd.generate_or_load(tmp_path, spec, 8, 0, FAST, progress=False)
    meta = json.loads((tmp_path / META_FILE).read_text())
    assert meta["source"] == "cosserat" and meta["options"]["steps_per_segment"] == 4
    assert meta["options"]["gravity"] == [-9.81, 0.0, 0.0]
    calls = []
    real = cd.generate
    monkeypatch.setattr(cd, "generate", lambda *a, **k: calls.append(a) or real(*a, **k))
    again = cd.generate_or_load(tmp_path, spec, 8, 0, FAST, progress=False)
    assert calls == [] and all(torch.equal(first[k], again[k]) for k in first)
    other = cd.CosseratOptions(steps_per_segment=4, tension_max=1.0)
    changed = cd.generate_or_load(tmp_path, spec, 8, 0, other, progress=False)
    assert len(calls) == 1 and not torch.equal(changed["q"], first["q"])
    assert json.loads((tmp_path / META_FILE).read_text())["options"]["tension_max"] == 1.0
    # the same directory asked for a CC dataset: another source, regenerated; meta says "cc"
    cc_generate_or_load(tmp_path, spec, 8, 0, SamplerOptions())
    assert json.loads((tmp_path / META_FILE).read_text())["source"] == "cc"


def test_a_modified_dataset_is_refused(spec, tmp_path):
    data = cd.generate_or_load(tmp_path, spec, 6, 0, FAST, progress=False)
    data["q"][0, 0] += 1e-3
    torch.save(data, tmp_path / TENSOR_FILE)
    with pytest.raises(ValueError, match="checksum mismatch"):
        load_dataset(tmp_path, spec)
    with pytest.raises(ValueError, match="checksum mismatch"):
        cd.generate_or_load(tmp_path, spec, 6, 0, FAST, progress=False)


@pytest.mark.parametrize("options", [cd.CosseratOptions(steps_per_segment=4, max_iter=1),
                                     cd.CosseratOptions(steps_per_segment=4, tension_max=500.0)])
def test_failed_samples_are_rejected_and_nothing_is_written(spec, tmp_path, options):
    target = tmp_path / "cache"
    with pytest.raises(ConvergenceError, match=r"Cosserat dataset: \d+ of 6 samples failed \(worst shooting residual "
                                               r".*nothing was written.*tension_max.*max_iter"):
        cd.generate_or_load(target, spec, 6, 0, options, progress=False)
    assert not target.exists() or list(target.iterdir()) == []


def test_train_py_shows_a_failed_generation_as_one_error_line(tmp_path, capsys):
    config = write_run_config(tmp_path, robot="configs/robots/tdcr_3seg_cosserat.yaml", epochs=1, n_train=8, n_val=4,
                              n_test=4, source="cosserat", cosserat={"steps_per_segment": 2, "max_iter": 1},
                              cache_dir=str(tmp_path / "data"))
    assert train.run_command_line(["fit", "--config", str(config)]) != 0
    err = capsys.readouterr().err
    assert "error:" in err and "samples failed" in err and "Traceback" not in err
    assert not (tmp_path / "data" / TENSOR_FILE).exists()


def test_bad_options_and_a_robot_without_mechanics_are_refused(spec):
    with pytest.raises(ValueError, match=r"data.cosserat: unknown option\(s\) \['tension'\]"):
        cd.CosseratOptions.from_dict({"tension": 1.0})
    with pytest.raises(ValueError, match="gravity: expected 3 finite numbers"):
        cd.CosseratOptions(gravity=(0.0, 9.81))
    with pytest.raises(ValueError, match="tendons_pulled: got 5, expected at most 4"):
        cd.generate(spec, 2, 0, cd.CosseratOptions(tendons_pulled=5), progress=False)
    plain = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
    with pytest.raises(ValueError, match="source 'cosserat' needs a robot description with a mechanics: block"):
        KinematicsDataModule(robot=str(plain), source="cosserat")
    with pytest.raises(ValueError, match="needs a mechanics: block"):
        cd.generate(RobotSpec.from_yaml(plain), 2, 0, progress=False)
    with pytest.raises(ValueError, match="source: expected 'cc' or 'cosserat'"):
        KinematicsDataModule(robot=str(ROBOT), source="fem")
    with pytest.raises(ValueError, match="noise options are not supported"):
        KinematicsDataModule(robot=str(ROBOT), source="cosserat", joint_noise=1e-4)


def test_without_gravity_and_tendon_compliance_the_pose_is_the_cc_model_of_the_joint_lengths(spec):
    """The closed form of docs/cosserat.md §2: piecewise CC arcs whose Clarke features are those of the
    tendon lengths. RK4's error falls as steps⁻⁴ (8 steps: ≈ 1e-6 l); gravity breaks the equality."""
    rigid = RobotSpec.from_dict({**spec.to_dict(), "mechanics": {**spec.mechanics.to_dict(), "tendon_compliance": 0.0}})
    length, errors = rigid.total_length, []
    for steps in (8, 16):
        options = cd.CosseratOptions(gravity=(0.0, 0.0, 0.0), steps_per_segment=steps)
        data = cd.generate(rigid, 32, 0, options, dtype=torch.float64, progress=False)
        cc = forward_kinematics(rigid, ClarkeEncoder(rigid)(data["q"]))
        errors.append(float((cc[:, :3, 3] - data["pose"][:, :3, 3]).norm(dim=-1).max() / length))
        assert torch.allclose(cc[:, :3, :3], data["pose"][:, :3, :3], atol=3e-3 * (4 / steps) ** 4)
    assert errors[0] < 1.5e-5 and errors[1] < errors[0] / 12      # measured 9.0e-6, 5.6e-7: RK4's order 4
    assert cd.cc_baseline(rigid, data["q"], data["pose"])["cc_pos_err_mean_pct"] < 2e-4
    assert float(data["features"][..., :2].norm(dim=-1).max()) > 0.3 * rigid.segments[0].radius   # bent shapes
    heavy = cd.generate(rigid, 64, 0, cd.CosseratOptions(steps_per_segment=8), dtype=torch.float64, progress=False)
    assert cd.cc_baseline(rigid, heavy["q"], heavy["pose"])["cc_pos_err_mean_pct"] > 0.1   # sag: ≥ 0.1 % of length


def test_the_datamodule_and_train_py_serve_a_cosserat_dataset_and_report_the_cc_baseline(tmp_path):
    config = write_run_config(tmp_path, robot="configs/robots/tdcr_3seg_cosserat.yaml", epochs=1, n_train=128,
                              n_val=32, n_test=48, batch_size=32, source="cosserat",
                              cosserat={"steps_per_segment": 2, "tension_max": 1.0},
                              cache_dir=str(tmp_path / "data"))
    cli = train.main(["fit", "--config", str(config)])
    dm = cli.datamodule
    assert dm.source == "cosserat" and dm.options.steps_per_segment == 2
    assert "segment_frames" not in dm.splits["train"] and dm.splits["test"]["q"].shape == (48, 12)
    assert json.loads((tmp_path / "data" / META_FILE).read_text())["source"] == "cosserat"
    summary = json.loads((tmp_path / "runs" / "smoke" / "version_0" / "metrics.json").read_text())
    assert summary["source"] == "cosserat"
    expected = cd.cc_baseline(dm.spec, dm.splits["test"]["q"], dm.splits["test"]["pose"])
    assert summary["cc_pos_err_mean_pct"] == pytest.approx(expected["cc_pos_err_mean_pct"]) and expected[
        "cc_pos_err_mean_pct"] > 0.05
    assert "cc_rot_err_mean_deg" in summary
    visual = cli.model.visual_batch()      # the Rerun scene: CC backbone of the features and the Cosserat one
    assert visual["backbone_true"].shape == (8, 7, 3) and visual["backbone"].shape[0] == 8
    assert torch.equal(visual["backbone_true"], dm.splits["val"]["backbone"][:8])


def test_the_ablation_runner_trains_and_tests_on_cached_cosserat_data(tmp_path):
    from dacr_learn.ablation.runner import Job, conditions, run_job

    cfg = {"robots": {"cos": str(ROBOT)}, "tasks": ["fk"], "features": ["clarke"], "n_train": [64], "seeds": [0],
           "model": {"width": 16, "depth": 2, "lr": 1e-2}, "train": {"steps": 4, "batch_size": 32},
           "test": {"n": 32, "seed": 7}, "conditions": {},
           "data": {"source": "cosserat", "cosserat": {"steps_per_segment": 2}, "cache_dir": str(tmp_path)}}
    job = Job("cos", "fk", "clarke", 64, 0)
    assert conditions(cfg, job) == ["clean"]
    (row,) = run_job(cfg, job)
    assert row["condition"] == "clean" and row["pos_err_mean_pct"] > 0 and row["cc_pos_err_mean_pct"] > 0.05
    cached = sorted(p.name for p in tmp_path.iterdir())
    assert cached == ["tdcr-3seg-cosserat_n32_seed7", "tdcr-3seg-cosserat_n64_seed1"]


def test_ik_with_the_cc_pose_loss_is_refused_on_cosserat_data(tmp_path, capsys):
    """IK's pose loss is the CC FK of the predicted joints: on Cosserat poses it would train towards the wrong
    model, so a pose_weight > 0 is refused in one line; the joint-space loss alone trains."""
    import yaml

    config = write_run_config(tmp_path, task="IKModule", robot="configs/robots/tdcr_3seg_cosserat.yaml", epochs=1,
                              n_train=128, n_val=16, n_test=16, batch_size=32, source="cosserat",
                              cosserat={"steps_per_segment": 2, "tension_max": 1.0}, cache_dir=str(tmp_path / "data"))
    cfg = yaml.safe_load(config.read_text())
    cfg["model"]["init_args"]["pose_weight"] = 1.0
    config.write_text(yaml.safe_dump(cfg))
    assert train.run_command_line(["fit", "--config", str(config)]) != 0
    err = capsys.readouterr().err
    assert "error:" in err and "pose_weight" in err and "'cosserat'" in err and "Traceback" not in err
    cfg["model"]["init_args"]["pose_weight"] = 0.0
    config.write_text(yaml.safe_dump(cfg))
    assert train.run_command_line(["fit", "--config", str(config)]) == 0
