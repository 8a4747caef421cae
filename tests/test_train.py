"""End to end: train.py (LightningCLI) → metrics.json, rerun.rrd, checkpoints; resume; DDP."""
import json
import os
import subprocess
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
import yaml
from conftest import write_run_config

import train
from dacr_learn.training import FKModule

RERUN = Path(sys.executable).parent / "rerun"


def batch_loss(module, split):
    with torch.no_grad():
        return module.loss({"q": split["q"], "pose": split["pose"]}).item()


def test_fit_writes_summary_recording_and_checkpoint_and_loss_goes_down(tmp_path, monkeypatch):
    monkeypatch.setenv(train.RUN_FOLDER_ENV, "")
    monkeypatch.setenv(train.OUT_FOLDER_ENV, "")
    cli = train.main(["fit", "--config", str(write_run_config(tmp_path))])
    run = tmp_path / "runs" / "smoke" / "version_0"
    # rank 0 names its folder in the environment that a DDP launcher copies to the worker processes
    assert os.environ[train.RUN_FOLDER_ENV] == os.environ[train.OUT_FOLDER_ENV] == str(run.resolve())
    summary = json.loads((run / "metrics.json").read_text())
    for key in ("pos_err_mean_mm", "pos_err_p95_mm", "pos_err_mean_pct", "rot_err_mean_deg", "train_seconds"):
        assert key in summary and summary[key] == summary[key]
    assert summary["n_test"] == 300 and summary["features"] == "clarke"
    assert yaml.safe_load((run / "config.yaml").read_text())["data"]["n_train"] == 2000   # saved per run
    # the loss went down: trained model vs a freshly initialised one with the same normalisation
    val = cli.datamodule.splits["val"]
    fresh = FKModule(robot=cli.model.spec.to_dict(), width=32, depth=2)
    fresh.model.fit_normalization(cli.datamodule.splits["train"]["q"])
    assert batch_loss(cli.model, val) < 0.2 * batch_loss(fresh, val)
    # the recording is complete and readable
    rrd = run / "rerun.rrd"
    assert rrd.stat().st_size > 0
    verify = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    # the checkpoint rebuilds the identical model, loads with weights_only=True, carries spec + config
    ckpt = run / "checkpoints" / "last.ckpt"
    raw = torch.load(ckpt, weights_only=True)
    assert raw["hyper_parameters"]["robot"] == cli.model.spec.to_dict()
    assert "n_train: 2000" in raw["dacr_config"]
    loaded = FKModule.load_from_checkpoint(ckpt, weights_only=True).eval()
    cli.model.eval()
    with torch.no_grad():
        assert torch.equal(loaded(val["q"]), cli.model(val["q"]))


class CountSteps(pl.Callback):
    def __init__(self):
        self.steps = 0

    def on_train_batch_end(self, *args):
        self.steps += 1


class CrashAt(pl.Callback):
    def __init__(self, step):
        self.step = step

    def on_train_batch_end(self, trainer, *args):
        if trainer.global_step == self.step:
            raise RuntimeError("simulated crash")


def test_interrupted_run_resumes_from_last_checkpoint(tmp_path):
    cfg = str(write_run_config(tmp_path, epochs=2))
    steps_per_epoch = 2000 // 64 + 1
    cli = train.main(["--config", cfg], run=False)
    cli.trainer.callbacks.append(CrashAt(steps_per_epoch + 5))            # in the middle of epoch 2
    with pytest.raises(RuntimeError, match="simulated crash"):
        cli.trainer.fit(cli.model, cli.datamodule)
    last = tmp_path / "runs" / "smoke" / "version_0" / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=True)["global_step"] == steps_per_epoch + 5
    resumed = train.main(["--config", cfg], run=False)
    counter = CountSteps()
    resumed.trainer.callbacks.append(counter)
    resumed.trainer.fit(resumed.model, resumed.datamodule, ckpt_path=str(last))
    assert resumed.trainer.current_epoch == 2
    assert resumed.trainer.global_step == 2 * steps_per_epoch
    assert counter.steps == steps_per_epoch - 5                           # only the unfinished part re-ran


def test_ik_training_keeps_the_constraint_and_reports_ik_metrics(tmp_path):
    config = write_run_config(tmp_path, task="IKModule", robot="configs/robots/tdcr_3seg_coupled.yaml")
    train.main(["fit", "--config", str(config)])
    summary = json.loads((tmp_path / "runs" / "smoke" / "version_0" / "metrics.json").read_text())
    assert summary["task"] == "ik"
    assert summary["constraint_residual_max_m"] <= 1e-6
    assert summary["joint_err_mean_mm"] > 0 and summary["pos_err_mean_mm"] > 0


@pytest.mark.slow
def test_ddp_with_two_cpu_processes_matches_single_process_evaluation(tmp_path):
    cfg = write_run_config(tmp_path, epochs=1)
    env = {**os.environ, "PYTHONPATH": os.getcwd()}
    proc = subprocess.run([sys.executable, "train.py", "fit", "--config", str(cfg), "--trainer.devices", "2",
                           "--trainer.strategy", "ddp"], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = tmp_path / "runs" / "smoke" / "version_0"
    assert [p.name for p in (tmp_path / "runs" / "smoke").iterdir()] == ["version_0"]   # one run, not one per rank
    summary = json.loads((run / "metrics.json").read_text())
    # the all-gathered DDP test metrics equal a single-process evaluation of the same checkpoint
    module = FKModule.load_from_checkpoint(run / "checkpoints" / "last.ckpt", weights_only=True)
    dm = train.KinematicsDataModule(**yaml.safe_load(cfg.read_text())["data"])
    pl.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False).test(module, dm, verbose=False)
    assert module.test_summary["pos_err_mean_mm"] == pytest.approx(summary["pos_err_mean_mm"], rel=1e-5)
    assert module.test_summary["pos_err_max_mm"] == pytest.approx(summary["pos_err_max_mm"], rel=1e-5)


def test_ddp_workers_use_the_folders_rank_0_made_not_the_newest(tmp_path):
    """Two DDP jobs of one run name started together: job A's rank 0 makes version_0, job B's version_1 before
    A's workers start; A's workers must write to version_0 (rank 0 passes its folders to the processes it
    launches through their environment), not to the newest version."""
    root = tmp_path / "runs" / "smoke"
    mine, newer = (root / "version_0"), (root / "version_1")
    for folder in (mine, newer, mine / "test_0"):
        folder.mkdir(parents=True)
    env = {train.RUN_FOLDER_ENV: str(mine), train.OUT_FOLDER_ENV: str(mine)}
    assert train.worker_folders(root, "fit", None, env) == (mine, mine)
    env[train.OUT_FOLDER_ENV] = str(mine / "test_0")
    assert train.worker_folders(root, "test", None, env) == (mine, mine / "test_0")
    assert train.worker_folders(root, "fit", None, {}) == (newer, newer)       # without them: the old guess
