"""The learned IK sampler (dacr_learn.sampler, training_sampler): samples inside the limits, a likelihood that training
raises, checkpoints that load_model returns and that seed solve_ik and the IK CLI, clear errors on bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml
from conftest import ROOT, random_features, reference_joint_vector
from rerun.chunk import RrdReader
from rerun_testkit import rrd_data, rrd_verify, rrd_views

import train
from dacr_learn import load_model
from dacr_learn.cli.ik import main as ik_cli
from dacr_learn.data import generate
from dacr_learn.ik import clarke_limits, solve_ik
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.metrics import rotation_geodesic
from dacr_learn.robot import RobotSpec
from dacr_learn.sampler import ClarkeSampler, LimitSquash
from dacr_learn.training_sampler import SamplerModule
from dacr_learn.viz.layout import metric_groups

F64 = torch.float64
TDCR3 = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
HETERO = ROOT / "configs" / "robots" / "hetero_4seg_types.yaml"     # types 0, I, II, III: every kind of limit


def sampler_config(tmp_path, features: str, position_fraction: float = 0.5) -> str:
    """A tiny sampler fit: 40 steps of a 2-transform flow on 1 000 samples of the 3-segment robot."""
    cfg = {"run_name": f"sampler_{features}", "runs_dir": str(tmp_path / "runs"), "seed_everything": 0,
           "trainer": {"accelerator": "cpu", "devices": 1, "max_steps": 40, "max_epochs": -1, "val_check_interval": 40,
                       "check_val_every_n_epoch": None, "enable_progress_bar": False, "log_every_n_steps": 10,
                       "enable_model_summary": False},
           "model": {"class_path": "dacr_learn.training_sampler.SamplerModule",
                     "init_args": {"features": features, "transforms": 2, "width": 32, "depth": 1, "lr": 5e-3,
                                   "noise": 0.02, "position_fraction": position_fraction, "visual_samples": 3}},
           "data": {"robot": str(TDCR3), "n_train": 1000, "n_val": 200, "n_test": 200, "batch_size": 100}}
    path = tmp_path / f"{features}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


@pytest.fixture(scope="module")
def clarke_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sampler")
    cli = train.main(["fit", "--config", sampler_config(tmp, "clarke")])
    return cli, tmp / "runs" / "sampler_clarke"


def reachable_poses(spec: RobotSpec, n: int, seed: int) -> torch.Tensor:
    return forward_kinematics(spec, random_features(spec, (n,), seed))


@pytest.mark.parametrize("robot", [TDCR3, HETERO])
def test_squash_maps_everything_inside_the_limits_and_inverts(robot):
    spec = RobotSpec.from_yaml(robot)
    squash, limits = LimitSquash(ClarkeSampler(spec).space), clarke_limits(spec)
    v = torch.randn(500, limits.num_variables, dtype=F64, generator=torch.Generator().manual_seed(0)) * 3
    v[:5] *= 1e4                                                        # far out: onto the limits, never beyond
    v[5:10] *= 1e-9                                                     # near 0: the tanh(s)/s branch
    x = squash(v)
    assert limits.inside(x).all()
    moderate = v[10:].clamp(-2, 2)          # the inverse is exact where tanh has not saturated (pair norms < 3)
    torch.testing.assert_close(squash.inverse(squash(moderate)), moderate, atol=1e-9, rtol=1e-9)
    inside = limits.sample(200, torch.Generator().manual_seed(1))
    torch.testing.assert_close(squash(squash.inverse(inside)), inside, atol=1e-12, rtol=0)


@pytest.mark.parametrize("features", ["clarke", "raw"])
@pytest.mark.parametrize("robot", [TDCR3, HETERO])
def test_samples_have_the_contract_shape_and_lie_inside_the_limits(features, robot):
    spec = RobotSpec.from_yaml(robot)
    model = ClarkeSampler(spec, features, transforms=2, width=16, depth=1)
    model.position_trained.fill_(True)
    q = ClarkeDecoder(spec)(random_features(spec, (300,), 0, dtype=torch.float32))
    model.fit_normalization(q, forward_kinematics(spec, ClarkeEncoder(spec)(q)))
    model.eval()
    limits = clarke_limits(spec)
    poses = reachable_poses(spec, 7, 1)
    for target in (poses, poses[:, :3, 3], poses.float()):
        f = model.sample_features(target, 5, temperature=3.0)          # a wide spread: samples reach the limits
        assert f.shape == (7, 5, spec.num_actuated_features) and f.dtype == F64
        assert limits.inside(f).all() and torch.isfinite(f).all()
        assert ((f[:, 1:] - f[:, :1]).abs().amax(-1) > 0).all()       # independent samples per target, not copies
    q = model.sample(poses, 4)                                          # joints on the constraint (NumPy geometry)
    feats = ClarkeEncoder(spec).to(F64)(q).numpy()
    for qi, fi in zip(q.reshape(-1, spec.num_joints).numpy(), feats.reshape(-1, spec.num_segments, 4), strict=True):
        assert np.abs(reference_joint_vector(spec, fi) - qi).max() < 1e-9


def test_fit_raises_the_likelihood_and_checkpoints_load_as_samplers(clarke_run):
    cli, run = clarke_run
    summary = json.loads((run / "version_0" / "metrics.json").read_text())
    assert summary["task"] == "sampler" and {"nll_mean", "pos_err_mean_mm", "rot_err_mean_deg"} <= set(summary)
    assert "out_of_limits_pct" not in summary          # inside the limits by construction: nothing to plot
    val, train_split = cli.datamodule.splits["val"], cli.datamodule.splits["train"]
    fresh = SamplerModule(robot=cli.model.spec.to_dict(), transforms=2, width=32, depth=1)
    fresh.model.fit_normalization(train_split["q"], train_split["pose"])
    cli.model.eval()
    with torch.no_grad():
        trained_nll = -cli.model.model.log_prob(val["q"], val["pose"]).mean()
        fresh_nll = -fresh.model.log_prob(val["q"], val["pose"]).mean()
    assert trained_nll < fresh_nll - 2.0                               # nats per sample: far beyond noise
    rrd = run / "version_0" / "rerun.rrd"                              # the recording: NLL plotted linear (signed)
    rrd_verify(rrd)
    latest = max(RrdReader(rrd).blueprints(),          # the last layout sent: the one plotting the most metrics
                 key=lambda bp: sum(len(v.get("query", [])) for v in rrd_views(rrd, bp).values()))
    queries = {v.get("name"): " ".join(v.get("query") or []) for v in rrd_views(rrd, latest).values()}
    assert "metrics/train/nll" in queries["negative log-likelihood"] and "metrics/val/nll_mean" in queries[
        "negative log-likelihood"]
    assert "metrics_log10/val/pos_err_mean_mm" in queries["tip position error [mm], log10"]
    assert "/scene/backbone_pred" in rrd_data(rrd)                     # the sampled configurations as ghosts
    net = load_model(run)
    assert net.task == "sampler" and net.spec == cli.model.spec and isinstance(net, ClarkeSampler)
    poses = reachable_poses(net.spec, 3, 2)
    torch.manual_seed(0)
    a = net.sample_features(poses, 2)
    torch.manual_seed(0)
    b = cli.model.model.sample_features(poses, 2)
    torch.testing.assert_close(a, b, atol=0, rtol=0)                   # the same network came back (same dtype)


def test_a_trained_sampler_seeds_solve_ik(clarke_run):
    cli, _ = clarke_run
    net = cli.model.model.eval()
    spec = net.spec
    poses = reachable_poses(spec, 10, 3)
    seeds = net.sample_features(poses, 4)
    result = solve_ik(spec, poses, n_solutions=4, seeds=seeds)
    assert result.success.all()
    tips = forward_kinematics(spec, ClarkeEncoder(spec).to(F64)(result.q))
    assert (tips[..., :3, 3] - poses[:, None, :3, 3]).norm(dim=-1).max() <= 1e-6
    assert rotation_geodesic(tips[..., :3, :3], poses[:, None, :3, :3]).max() <= 1e-5


@pytest.mark.parametrize("position_only", [False, True])
def test_the_ik_cli_seeds_from_a_sampler_run(clarke_run, tmp_path, position_only, capsys):
    _, run = clarke_run
    spec = RobotSpec.from_yaml(TDCR3)
    poses = reachable_poses(spec, 6, 4)
    targets = poses[:, :3, 3] if position_only else poses
    np.save(tmp_path / "T.npy", targets.numpy())
    out = tmp_path / "S.npz"
    ik_cli(["--ckpt", str(run), "--targets", str(tmp_path / "T.npy"), "--out", str(out), "--solutions", "3"]
           + ["--position-only"] * position_only)
    assert "seeded by its learned sampler" in capsys.readouterr().out
    s = np.load(out)
    assert s["q"].shape == (6, 3, spec.num_joints) and s["q"].dtype == np.float64 and s["success"].all()
    tips = forward_kinematics(spec, ClarkeEncoder(spec).to(F64)(torch.from_numpy(s["q"])))
    assert (tips[..., :3, 3] - poses[:, None, :3, 3]).norm(dim=-1).max() <= 1e-6


def test_raw_sampler_trains_and_projects_its_samples(tmp_path):
    cli = train.main(["fit", "--config", sampler_config(tmp_path, "raw", position_fraction=0.0)])
    summary = json.loads((tmp_path / "runs" / "sampler_raw" / "version_0" / "metrics.json").read_text())
    assert summary["features"] == "raw" and summary["constraint_residual_mean_m"] > 0   # off the constraint
    assert 0 <= summary["out_of_limits_pct"] <= 100
    net = load_model(tmp_path / "runs" / "sampler_raw")
    poses = reachable_poses(net.spec, 5, 5)
    assert clarke_limits(net.spec).inside(net.sample_features(poses, 6, temperature=3.0)).all()   # projected
    with pytest.raises(ValueError, match="trained on whole poses only"):
        net.sample_features(poses[:, :3, 3], 2)                       # position_fraction 0: poses only
    assert not cli.model.model.position_trained


@pytest.mark.parametrize("target, count, temperature, message", [
    (torch.zeros(3, 4), 2, 1.0, "expected \\(B, 4, 4\\) tip poses or \\(B, 3\\) tip positions"),
    (torch.zeros(0, 3), 2, 1.0, "B >= 1"),
    (torch.full((2, 3), float("nan")), 2, 1.0, "NaN/inf"),
    (torch.zeros(2, 3, dtype=torch.long), 2, 1.0, "floating-point"),
    (torch.zeros(2, 3), 0, 1.0, "count: expected an integer >= 1"),
    (torch.zeros(2, 3), 2.5, 1.0, "count: expected an integer >= 1"),
    (torch.zeros(2, 3), 2, 0.0, "temperature: expected a finite number > 0"),
])
def test_bad_sampling_input_raises_a_value_error(target, count, temperature, message):
    model = ClarkeSampler(RobotSpec.from_yaml(TDCR3), transforms=1, width=8, depth=1)
    model.position_trained.fill_(True)
    with pytest.raises(ValueError, match=message):
        model.sample_features(target, count, temperature)


@pytest.mark.parametrize("kwargs, message", [
    ({"features": "joints"}, "features: expected one of"),
    ({"transforms": 0}, "transforms: expected an integer >= 1"),
    ({"bins": 1}, "bins: expected an integer >= 2"),
    ({"activation": "swish"}, "activation: expected one of"),
    ({"noise": -0.1}, "noise: expected a standard deviation >= 0"),
    ({"features": "raw", "noise": 0.0}, "expected noise > 0 with features 'raw'"),
    ({"position_fraction": 1.5}, "position_fraction: expected a fraction in \\[0, 1\\]"),
])
def test_bad_settings_raise_a_value_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SamplerModule(robot=str(TDCR3), **kwargs)


def test_generated_data_and_sampler_agree_on_the_variables():
    """The flow's "clarke" variables of a dataset's joints map back, through the squash, to the dataset's features."""
    spec = RobotSpec.from_yaml(TDCR3)
    data = generate(spec, 50, 0, dtype=F64)
    model = ClarkeSampler(spec).to(F64)
    f = model.squash(model.variables(data["q"].to(F64)))
    selected = data["features"].to(F64).flatten(-2) @ model.selection.mT
    torch.testing.assert_close(f, selected, atol=1e-6 * spec.total_length, rtol=0)


def test_recording_layout_names_the_sampler_quantities():
    groups = metric_groups(["train/nll", "val/nll_mean", "val/out_of_limits_pct", "val/pos_err_mean_pct"])
    assert groups == {"negative log-likelihood": ["train/nll", "val/nll_mean"],
                      "outside the joint limits [% of samples]": ["val/out_of_limits_pct"],
                      "tip position error [% of robot length]": ["val/pos_err_mean_pct"]}
