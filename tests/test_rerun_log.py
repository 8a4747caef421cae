"""Tests of dacr_learn.rerun_log: the Rerun Lightning logger, the visual callback, scene helpers.

Every recording is written under pytest's tmp_path, checked with ``rerun rrd verify`` and
read back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import pytest
import rerun as rr
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from rerun.chunk import RrdReader
from torch.utils.data import DataLoader, TensorDataset

from dacr_learn.rerun_log import (
    RerunLogger,
    RerunVisualCallback,
    default_blueprint,
    find_rerun_logger,
    log_path,
    log_scene,
    metric_entity,
)

K, P, N = 3, 9, 40


def _rerun_cli() -> str:
    local = Path(sys.executable).parent / "rerun"
    cli = str(local) if local.exists() else shutil.which("rerun")
    if cli is None:
        pytest.skip("rerun CLI not installed")
    return cli


def _verify(path: Path) -> None:
    proc = subprocess.run(
        [_rerun_cli(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def _chunks(path: Path) -> dict[str, list]:
    """Entity path -> list of pyarrow RecordBatches of the recording in ``path``."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches: list, name: str) -> list:
    return [v for rb in batches if name in rb.schema.names for v in rb.column(name).to_pylist()]


def _blueprint_origins(path: Path, store) -> set[str]:
    origins: set[str] = set()
    for chunk in RrdReader(path).stream(store=store):
        rb = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in rb.schema.names:
            rows = rb.column("ViewBlueprint:space_origin").to_pylist()
            origins.update(o for row in rows for o in row)
    return origins


def _random_visual() -> dict[str, torch.Tensor]:
    pose_true = torch.eye(4).repeat(K, 1, 1)
    pose_true[:, :3, 3] = torch.rand(K, 3) * 0.1
    pose_pred = pose_true.clone()
    pose_pred[:, :3, 3] += 0.002 * torch.randn(K, 3)
    return {
        "backbone": torch.rand(K, P, 3) * 0.1,
        "pose_true": pose_true,
        "pose_pred": pose_pred,
        "workspace_points": torch.rand(N, 3) * 0.1,
        "workspace_error": torch.rand(N) * 0.003,
    }


class TinyModule(pl.LightningModule):
    def __init__(self, lr: float = 0.01) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.net = torch.nn.Linear(3, 3)

    def training_step(self, batch, batch_idx):
        x, y = batch
        loss = torch.nn.functional.mse_loss(self.net(x), y)
        self.log("train_loss", loss)
        return loss

    def validation_step(self, batch, batch_idx):
        x, y = batch
        err = (self.net(x) - y).norm(dim=-1)
        self.log("val_loss", err.pow(2).mean())
        self.log("val/pos_err", err.mean())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=self.hparams.lr)

    def train_dataloader(self):
        g = torch.Generator().manual_seed(0)
        data = TensorDataset(torch.randn(32, 3, generator=g), torch.randn(32, 3, generator=g))
        return DataLoader(data, batch_size=8)

    def val_dataloader(self):
        return DataLoader(TensorDataset(torch.randn(16, 3), torch.randn(16, 3)), batch_size=8)


class VisualModule(TinyModule):
    def visual_batch(self) -> dict[str, torch.Tensor]:
        return _random_visual()


def _fit(module: pl.LightningModule, logger, callbacks, epochs: int = 2) -> pl.Trainer:
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=logger,
        callbacks=callbacks,
        accelerator="cpu",
        devices=1,
        log_every_n_steps=1,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*does not have many workers.*")
        trainer.fit(module)
    return trainer


def test_fit_writes_verified_rrd_with_metrics_and_scene(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="tiny")
    trainer = _fit(VisualModule(), logger, [RerunVisualCallback()])
    path = tmp_path / "tiny" / "rerun.rrd"
    assert logger.rrd_path == str(path) and logger.log_dir == str(tmp_path / "tiny")
    assert path.exists() and path.stat().st_size > 0
    _verify(path)
    chunks = _chunks(path)
    for entity in ("/metrics/train_loss", "/metrics/val_loss", "/metrics/val/pos_err"):
        assert entity in chunks, sorted(chunks)
    values = _column(chunks["/metrics/train_loss"], "Scalars:scalars")
    steps = _column(chunks["/metrics/train_loss"], "step")
    assert len(values) == trainer.global_step == 8  # 4 batches x 2 epochs, logged every step
    assert all(np.isfinite(v[0]) for v in values) and steps == sorted(steps)
    # one scene per validation epoch (sanity check skipped), at the global step
    assert _column(chunks["/scene/backbone"], "step") == [4, 8]
    assert _column(chunks["/scene/tip_true"], "step") == [4, 8]
    arrows = _column(chunks["/scene/tip_pred"], "Arrows3D:vectors")
    assert len(arrows[0]) == 3 * K
    assert len(_column(chunks["/scene/workspace"], "Points3D:colors")[0]) == N
    assert "max tip error" in _column(chunks["/scene/workspace"], "TextLog:text")[0][0]
    assert '"lr": 0.01' in _column(chunks["/hparams"], "TextDocument:text")[0][0]
    assert _column(chunks["/run/status"], "TextLog:text") == [["run success"]]
    # the default blueprint is re-sent when new metrics appear: one plot per metric
    wanted = {"metrics/train_loss", "metrics/val_loss", "metrics/val/pos_err", "scene"}
    assert any(wanted <= _blueprint_origins(path, bp) for bp in RrdReader(path).blueprints())


def test_callback_without_visual_batch_is_harmless(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="novis")
    with pytest.warns(UserWarning, match="visual_batch"):
        _fit(TinyModule(), logger, [RerunVisualCallback()], epochs=1)
    path = tmp_path / "novis" / "rerun.rrd"
    _verify(path)
    chunks = _chunks(path)
    assert "/metrics/val_loss" in chunks
    assert not [e for e in chunks if e.startswith("/scene/")]


def test_callback_without_rerun_logger_does_nothing(tmp_path):
    class Exploding(TinyModule):
        def visual_batch(self):
            raise AssertionError("must not be called without a RerunLogger")

    trainer = _fit(Exploding(), False, [RerunVisualCallback()], epochs=1)
    assert find_rerun_logger(trainer) is None
    assert not list(tmp_path.iterdir())


def test_every_n_epochs(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="every2")
    _fit(VisualModule(), logger, [RerunVisualCallback(every_n_epochs=2)], epochs=3)
    assert _column(_chunks(tmp_path / "every2" / "rerun.rrd")["/scene/backbone"], "step") == [8]
    with pytest.raises(ValueError, match="every_n_epochs"):
        RerunVisualCallback(every_n_epochs=0)


def test_logger_reused_after_finalize_writes_next_part(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="parts", version=3)
    logger.log_metrics({"a": 1.0}, step=0)
    logger.finalize("success")
    logger.log_metrics({"a": torch.tensor(2.0)}, step=1)
    logger.finalize("success")
    first, second = (tmp_path / "parts" / "version_3" / f"{f}.rrd" for f in ("rerun", "rerun_1"))
    for path, value in ((first, 1.0), (second, 2.0)):
        _verify(path)
        assert _column(_chunks(path)["/metrics/a"], "Scalars:scalars") == [[value]]
    ids = {r.recording_id for p in (first, second) for r in RrdReader(p).recordings()}
    assert len(ids) == 1  # the viewer merges both parts into one recording


def test_logger_properties_and_pickling(tmp_path):
    import pickle

    logger = RerunLogger(save_dir=tmp_path, name="props")
    assert (logger.name, logger.version, logger.save_dir) == ("props", "", str(tmp_path))
    assert isinstance(logger.experiment, rr.RecordingStream)
    assert logger.recording is logger.experiment
    clone = pickle.loads(pickle.dumps(logger))
    assert clone.name == "props" and clone._rec is None
    logger.finalize("success")
    named = RerunLogger(save_dir=tmp_path, version="run-a")
    assert named.log_dir == str(tmp_path / "default" / "run-a")
    with pytest.raises(ValueError, match="save_dir"):
        RerunLogger(save_dir=None)


def test_nonzero_rank_logs_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(rank_zero_only, "rank", 1)
    logger = RerunLogger(save_dir=tmp_path, name="rank1")
    logger.log_metrics({"a": 1.0}, step=0)
    logger.log_hyperparams({"lr": 0.1})
    logger.experiment.log("x", rr.Scalars(1.0))  # the dummy experiment swallows calls
    logger.finalize("success")
    assert not (tmp_path / "rank1").exists()


def test_log_scene_outside_lightning(tmp_path):
    path = tmp_path / "scene.rrd"
    rec = rr.RecordingStream("dacr_learn_test")
    rec.set_sinks(rr.FileSink(path))
    rec.set_time("step", sequence=5)
    visual = _random_visual()
    log_scene(rec, "ctrl", {"backbone": visual["backbone"], "pose_true": visual["pose_true"]})
    log_path(rec, "ctrl/target", np.zeros((4, 3)), color=(255, 0, 0))
    with pytest.raises(ValueError, match="unknown visual keys"):
        log_scene(rec, "ctrl", {"backbones": visual["backbone"]})
    with pytest.raises(ValueError, match=r"pose_pred.*\(…, 4, 4\)"):
        log_scene(rec, "ctrl", {"pose_pred": torch.eye(3)})
    rec.disconnect()
    _verify(path)
    chunks = _chunks(path)
    assert {"/ctrl/backbone", "/ctrl/tip_true", "/ctrl/target"} <= set(chunks)
    assert "/ctrl/tip_error" not in chunks and "/ctrl/workspace" not in chunks
    assert len(_column(chunks["/ctrl/backbone"], "LineStrips3D:strips")[0]) == K
    vectors = np.array(_column(chunks["/ctrl/tip_true"], "Arrows3D:vectors")[0])
    origins = np.array(_column(chunks["/ctrl/tip_true"], "Arrows3D:origins")[0])
    assert np.allclose(vectors, np.tile(0.01 * np.eye(3), (K, 1)))  # x, y, z axes, 1 cm
    assert np.allclose(origins, np.repeat(visual["pose_true"][:, :3, 3].numpy(), 3, axis=0))


def test_metric_entity_and_blueprint():
    assert metric_entity("val/pos_err") == "metrics/val/pos_err"
    assert metric_entity("loss step") == "metrics/loss\\ step"
    default_blueprint()
    default_blueprint(["train_loss", "val/pos_err"])


def test_spawn_starts_viewer_and_streams_to_it(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(rr, "spawn", lambda **kw: calls.append(kw))
    url = "rerun+http://127.0.0.1:9876/proxy"  # the spawned viewer's: not added twice
    logger = RerunLogger(save_dir=tmp_path, spawn=True, connect=url)
    sinks = logger._sinks(rr.RecordingStream("dacr_learn_test"))
    assert [type(s) for s in sinks] == [rr.FileSink, rr.GrpcSink]
    assert len(calls) == 1 and calls[0]["connect"] is False


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_connect_streams_to_running_server(tmp_path):
    port = _free_port()
    server = subprocess.Popen(
        [_rerun_cli(), "--serve-grpc", "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 10
        while socket.socket().connect_ex(("127.0.0.1", port)) != 0:
            assert time.monotonic() < deadline, "rerun --serve-grpc did not start"
            time.sleep(0.05)
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        logger = RerunLogger(save_dir=tmp_path, name="live", connect=url)
        logger.log_metrics({"a": 1.0}, step=0)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a failed flush to the server would warn
            logger.finalize("success")
    finally:
        server.terminate()
        server.wait(timeout=10)
    _verify(tmp_path / "live" / "rerun.rrd")
