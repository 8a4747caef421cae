"""dacr_learn.viz.callback: the visual callback (a visual batch per logged epoch, harmless without one or without a
RerunLogger, every_n_epochs) and the run's settings it records (run_info)."""
from __future__ import annotations

import lightning.pytorch as pl
import pytest
from rerun_testkit import TinyModule, VisualModule, fit_module, rrd_chunks, rrd_column, rrd_verify

from dacr_learn.viz.callback import RerunVisualCallback, find_rerun_logger
from dacr_learn.viz.logger import RerunLogger


def test_callback_without_visual_batch_is_harmless(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="novis")
    with pytest.warns(UserWarning, match="visual_batch"):
        fit_module(TinyModule(), logger, [RerunVisualCallback()], epochs=1)
    path = tmp_path / "novis" / "rerun.rrd"
    rrd_verify(path)
    chunks = rrd_chunks(path)
    assert "/metrics/val_loss" in chunks
    assert not [e for e in chunks if e.startswith("/scene/")]


def test_callback_without_rerun_logger_does_nothing(tmp_path):
    class Exploding(TinyModule):
        def visual_batch(self):
            raise AssertionError("must not be called without a RerunLogger")

    trainer = fit_module(Exploding(), False, [RerunVisualCallback()], epochs=1)
    assert find_rerun_logger(trainer) is None
    assert not list(tmp_path.iterdir())


def test_every_n_epochs(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="every2")
    fit_module(VisualModule(), logger, [RerunVisualCallback(every_n_epochs=2)], epochs=3)
    assert rrd_column(rrd_chunks(tmp_path / "every2" / "rerun.rrd")["/scene/backbone"], "step") == [8]
    with pytest.raises(ValueError, match="every_n_epochs"):
        RerunVisualCallback(every_n_epochs=0)


def test_run_info_records_seed_trainer_and_the_datamodules_settings(monkeypatch):
    from dacr_learn.datamodule import KinematicsDataModule
    from dacr_learn.viz.callback import run_info

    monkeypatch.setenv("PL_GLOBAL_SEED", "7")
    dm = KinematicsDataModule(n_train=10, n_val=2, n_test=3, batch_size=4, seed=5, joint_noise=1e-4)
    trainer = pl.Trainer(accelerator="cpu", max_epochs=3, gradient_clip_val=0.01, logger=False,
                         enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False)
    trainer.datamodule = dm
    info = run_info(trainer)
    assert info["seed"] == 7
    assert info["trainer"]["max_epochs"] == 3 and info["trainer"]["gradient_clip_val"] == 0.01
    data = info["data"]
    assert (data["class"], data["sizes"], data["batch_size"]) == ("KinematicsDataModule", [10, 2, 3], 4)
    assert data["seed"] == 5
    assert data["options"]["joint_noise"] == 1e-4 and data["spec"]["name"] == dm.spec.name
    assert "prepare_data_per_node" not in data and "splits" not in data  # Lightning's own / tensors: left out
