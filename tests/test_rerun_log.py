"""Tests of dacr_learn.rerun_log: the Rerun Lightning logger, the visual callback, scene helpers.

Every recording is written under pytest's tmp_path, checked with ``rerun rrd verify`` and
read back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import lightning.pytorch as pl
import numpy as np
import pytest
import rerun as rr
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from rerun.chunk import RrdReader
from torch.utils.data import DataLoader, TensorDataset

from dacr_learn.rerun_callback import RerunVisualCallback, find_rerun_logger
from dacr_learn.rerun_layout import metric_groups, series_style, summary_markdown
from dacr_learn.rerun_log import (
    RerunLogger,
    default_blueprint,
    log_path,
    log_scene,
    metric_entity,
)
from dacr_learn.rerun_scene import DEFAULT_ERROR_RANGE, error_colours, log_workspace

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


def _views(path: Path, store) -> dict[str, dict]:
    """View entity -> {"class", "name", "origin", "query", "ranges"} of one blueprint store in ``path``."""
    fields = {"ViewBlueprint:class_identifier": "class", "ViewBlueprint:display_name": "name",
              "ViewBlueprint:space_origin": "origin", "ViewContents:query": "query",
              "VisibleTimeRanges:ranges": "ranges"}
    views: dict[str, dict] = {}
    for chunk in RrdReader(path).stream(store=store):
        rb = chunk.to_record_batch()
        if not chunk.entity_path.startswith("/view/"):
            continue
        view = views.setdefault("/".join(chunk.entity_path.split("/")[:3]), {})
        for column, key in fields.items():
            if column in rb.schema.names:
                row = rb.column(column).to_pylist()[-1]
                view[key] = row if key in ("query", "ranges") else row[0]
    return views


def _time_panel(path: Path, store) -> dict[str, list]:
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream(store=store):
        if chunk.entity_path == "/time_panel":
            rb = chunk.to_record_batch()
            out.update({n: rb.column(n).to_pylist()[-1] for n in rb.schema.names if n.startswith("TimePanel")})
    return out


def _data_chunks(path: Path) -> int:
    return sum(1 for _ in RrdReader(path).stream())


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
    assert '"lr": 0.01' in _column(chunks["/hparams"], "TextDocument:text")[-1][0]
    assert _column(chunks["/run/status"], "TextLog:text") == [["run success"]]
    # log10 copies of train/val metrics for the log-scale plots; a legend name per series
    logs = _column(chunks["/metrics_log10/train_loss"], "Scalars:scalars")
    assert np.allclose(np.array(logs), np.log10(np.array(values)), atol=1e-6)
    assert _column(chunks["/metrics/val/pos_err"], "SeriesLines:names") == [["val"]]
    # the summary table holds the latest value of every metric; hparams carry seed, trainer and data
    table = _column(chunks["/summary"], "TextDocument:text")[-1][0]
    assert "| loss | " in table and "| pos_err |  | " in table  # rows: metric, columns: train, val
    hparams = _column(chunks["/hparams"], "TextDocument:text")[-1][0]
    assert all(f'"{k}"' in hparams for k in ("lr", "seed", "trainer", "max_epochs"))
    # batched rows: a few chunks per entity, not one per logged row
    assert max(len(b) for b in chunks.values()) <= 2 and _data_chunks(path) <= 2 * len(chunks)
    # the blueprint: full-range plots grouping the metrics, the scene views, opening at the last step
    # the last layout sent (stores are not ordered): the one plotting the most metrics
    blueprints = RrdReader(path).blueprints()
    latest = max(blueprints, key=lambda bp: sum(len(v.get("query", [])) for v in _views(path, bp).values()))
    views = list(_views(path, latest).values())
    plots = [v for v in views if v["class"] == "TimeSeries"]
    queried = {q for v in plots for q in v["query"]}
    assert {"metrics/train_loss", "metrics_log10/train_loss", "metrics/val/pos_err"} <= queried
    assert all(v["ranges"] == [{"timeline": "step", "range": {"start": None, "end": None}}] for v in plots)
    assert sum(v["class"] == "3D" and v["origin"] == "scene" for v in views) == 2
    panel = _time_panel(path, latest)
    assert panel["TimePanelBlueprint:timeline"] == ["step"] and panel["TimePanelBlueprint:play_state"] == [3]


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


def test_metric_groups_put_train_and_val_of_one_quantity_and_unit_together():
    names = ["epoch", "train/loss", "val/loss", "val/pos_err_mean_mm", "val/pos_err_p95_mm", "val/pos_err_mean_pct",
             "val/rot_err_mean_deg", "test/pos_err_mean_mm", "train_acc", "val_acc"]
    groups = metric_groups(names)
    assert groups == {"loss": ["train/loss", "val/loss"], "acc": ["train_acc", "val_acc"],
                      "tip position error [mm]": ["val/pos_err_mean_mm", "val/pos_err_p95_mm"],
                      "tip rotation error [°]": ["val/rot_err_mean_deg"]}
    assert list(groups)[0] == "loss"  # test metrics, epoch and the %-duplicate are in the table only
    assert series_style("val/pos_err_p95_mm")[0] == "val p95" and series_style("train_acc")[0] == "train acc"
    assert series_style("train/loss")[1] != series_style("val/loss")[1]
    table = summary_markdown({"val/pos_err_mean_mm": (10, 0.25), "test/pos_err_mean_mm": (12, 0.5), "epoch": (12, 3)})
    assert "| pos_err_mean_mm | 0.25 | 0.5 |  |" in table and "| epoch |  |  | 3 |" in table
    assert "step 12" in table


def test_workspace_colours_use_a_fixed_log_scale(tmp_path):
    lo, hi = DEFAULT_ERROR_RANGE
    errors = np.array([lo / 10, lo, 1e-4, hi, hi * 10])
    colours = error_colours(errors, DEFAULT_ERROR_RANGE)
    assert colours.shape == (5, 3) and colours.dtype == np.uint8
    assert (colours[0] == colours[1]).all() and (colours[3] == colours[4]).all()  # clipped at the ends
    # a colour depends on its own error only, not on the others (no per-frame rescaling)
    assert (error_colours(errors[2:3], DEFAULT_ERROR_RANGE) == colours[2]).all()
    assert np.abs(colours[3].astype(int) - colours[1]).sum() > 200  # the two ends differ clearly
    with pytest.raises(ValueError, match="error_range"):
        error_colours(errors, (1e-3, 1e-4))
    path = tmp_path / "ws.rrd"
    rec = rr.RecordingStream("dacr_learn_test")
    rec.set_sinks(rr.FileSink(path))
    pts = np.random.default_rng(0).random((1001, 3)) * 0.1
    max_err = log_workspace(rec, "ws", pts, np.linspace(0, 2e-3, 1001), max_points=100)
    rec.disconnect()
    assert max_err == pytest.approx(2e-3)
    shown = _column(_chunks(path)["/ws"], "Points3D:positions")[0]
    assert 90 <= len(shown) <= 100


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


def _group_members(pgid: int) -> list[int]:
    """Live processes of process group ``pgid`` (Linux /proc; empty elsewhere)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":  # fields: state, ppid, pgrp, …
            members.append(int(stat.parent.name))
    return members


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL, to the whole process group: the ``rerun`` wrapper and its viewer binary."""
    for sig, grace in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        deadline = time.monotonic() + grace
        while _group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not _group_members(proc.pid):
            break
    proc.wait(timeout=10)


def _serving(port: int, proc: subprocess.Popen) -> bool:
    """Wait until ``proc`` accepts connections on ``port`` (True) or exits (False, e.g. the port was taken)."""
    while proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.05)
    return False


@pytest.fixture
def grpc_server():
    """A ``rerun --serve-grpc`` in its own process group, killed as a group (no orphaned viewer)."""
    for _ in range(3):  # a free port may be taken before the server binds it: retry on a new one
        port = _free_port()
        proc = subprocess.Popen([_rerun_cli(), "--serve-grpc", "--port", str(port)], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            if _serving(port, proc):
                yield port
                return
        finally:
            _stop_group(proc)
            assert not _group_members(proc.pid), "a rerun process outlived the test"
    pytest.fail("rerun --serve-grpc exited before serving, three times")


def test_connect_streams_to_running_server(tmp_path, grpc_server):
    url = f"rerun+http://127.0.0.1:{grpc_server}/proxy"
    logger = RerunLogger(save_dir=tmp_path, name="live", connect=url)
    logger.log_metrics({"a": 1.0}, step=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a failed flush to the server would warn
        logger.finalize("success")
    _verify(tmp_path / "live" / "rerun.rrd")


class _FakeCC:
    """The CC model's backbone of a straight robot along z (enough for the recording)."""

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        return torch.linspace(0, 0.1, 5)[:, None] * torch.tensor([0.0, 0.0, 1.0]) + 0 * x[:, :1, None]


def test_hardware_recording_has_one_plot_with_every_model_and_opens_at_the_end(tmp_path):
    from dacr_learn.hardware.study.visual import log_rerun

    n, g = 30, torch.Generator().manual_seed(0)
    tip = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.05
    labels = tuple(["sweep"] * 15 + ["circle"] * 15)
    setup = SimpleNamespace(val=SimpleNamespace(tip=tip, x=torch.zeros(n, 4)), spec=SimpleNamespace(name="fake"),
                            val_rec=SimpleNamespace(labels=labels, source="val.csv"), cc=_FakeCC())
    preds = {f"model_{k}": tip + 0.001 * k * torch.randn(n, 3, generator=g, dtype=torch.float64) for k in range(10)}
    std = {"model_3": torch.full((n,), 0.002), "model_4": torch.full((n, 3), 0.001)}
    path = tmp_path / "hw.rrd"
    log_rerun(setup, preds, path, std=std)
    _verify(path)
    chunks = _chunks(path)
    assert {f"/errors/model_{k}" for k in range(10)} <= set(chunks)  # every model, not the first 8
    assert {"/sigma/model_3", "/sigma/model_4", "/world/band_2sigma/model_3"} <= set(chunks)
    assert len(_column(chunks["/errors/model_5"], "Scalars:scalars")) == n
    assert _column(chunks["/errors/model_5"], "SeriesLines:names")[0][0].startswith("model_5 (")
    twice_sigma = _column(chunks["/sigma/model_4"], "Scalars:scalars")[0][0]
    assert twice_sigma == pytest.approx(2e3 * 0.001 * np.sqrt(3), rel=1e-5)  # 2‖σ‖ [mm]
    # error plot and 3D path of a model share one colour
    line = _column(chunks["/errors/model_5"], "SeriesLines:colors")[0]
    strip = _column(chunks["/world/paths/model_5"], "LineStrips3D:colors")[0]
    assert line == strip
    assert _data_chunks(path) <= 3 * len(chunks)  # columns, not one chunk per sample
    (store,) = RrdReader(path).blueprints()
    views = _views(path, store).values()
    plots = [v for v in views if v["class"] == "TimeSeries"]
    assert sorted(v["origin"] for v in plots) == ["errors", "sigma"]  # one error plot (+ the 2σ one)
    assert any(v["class"] == "3D" and v["origin"] == "world" for v in views)
    assert _time_panel(path, store)["TimePanelBlueprint:play_state"] == [3]  # following: opens at the end
    # the 3D view shows the 3 lowest-RMSE models (and cc): the other paths are hidden there, not dropped
    hidden = set()
    for chunk in RrdReader(path).stream(store=store):
        rb = chunk.to_record_batch()
        if "EntityBehavior:visible" in rb.schema.names and rb.column("EntityBehavior:visible").to_pylist() == [[False]]:
            hidden.add(chunk.entity_path.split("/overrides/")[1].removesuffix("/visualizers"))
    assert {f"world/paths/model_{k}" for k in range(3, 10)} == {h for h in hidden if h.startswith("world/paths/")}
    (recording,) = RrdReader(path).recordings()
    assert recording.application_id == "dacr_learn_hardware"
    with pytest.raises(ValueError, match="std"):
        log_rerun(setup, preds, tmp_path / "bad.rrd", std={"model_0": torch.ones(n + 1)})


def test_run_info_records_seed_trainer_and_the_datamodules_settings(monkeypatch):
    from dacr_learn.datamodule import KinematicsDataModule
    from dacr_learn.rerun_callback import run_info

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
