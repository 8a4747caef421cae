"""Tests of dacr_learn.viz.logger: the Rerun Lightning logger (with the visual callback of a run), scene helpers
outside Lightning, the default blueprint, spawning / connecting to a viewer.

Every recording is written under pytest's tmp_path, checked with ``rerun rrd verify`` and
read back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41) through tests/rerun_testkit.py.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import torch
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from rerun.chunk import RrdReader
from rerun_testkit import (
    K,
    N,
    VisualModule,
    fit_module,
    random_visual,
    rerun_cli,
    rrd_chunks,
    rrd_column,
    rrd_data_chunks,
    rrd_time_panel,
    rrd_verify,
    rrd_views,
)

from dacr_learn.viz.callback import RerunVisualCallback
from dacr_learn.viz.logger import (
    RerunLogger,
    default_blueprint,
    log_path,
    log_scene,
    metric_entity,
)


def test_fit_writes_verified_rrd_with_metrics_and_scene(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="tiny")
    trainer = fit_module(VisualModule(), logger, [RerunVisualCallback()])
    path = tmp_path / "tiny" / "rerun.rrd"
    assert logger.rrd_path == str(path) and logger.log_dir == str(tmp_path / "tiny")
    assert path.exists() and path.stat().st_size > 0
    rrd_verify(path)
    chunks = rrd_chunks(path)
    for entity in ("/metrics/train_loss", "/metrics/val_loss", "/metrics/val/pos_err"):
        assert entity in chunks, sorted(chunks)
    values = rrd_column(chunks["/metrics/train_loss"], "Scalars:scalars")
    steps = rrd_column(chunks["/metrics/train_loss"], "step")
    assert len(values) == trainer.global_step == 8  # 4 batches x 2 epochs, logged every step
    assert all(np.isfinite(v[0]) for v in values) and steps == sorted(steps)
    # one scene per validation epoch (sanity check skipped), at the global step
    assert rrd_column(chunks["/scene/backbone"], "step") == [4, 8]
    assert rrd_column(chunks["/scene/tip_true"], "step") == [4, 8]
    arrows = rrd_column(chunks["/scene/tip_pred"], "Arrows3D:vectors")
    assert len(arrows[0]) == 3 * K
    assert len(rrd_column(chunks["/scene/workspace"], "Points3D:colors")[0]) == N
    assert "max tip error" in rrd_column(chunks["/scene/workspace"], "TextLog:text")[0][0]
    assert '"lr": 0.01' in rrd_column(chunks["/hparams"], "TextDocument:text")[-1][0]
    assert rrd_column(chunks["/run/status"], "TextLog:text") == [["run success"]]
    # log10 copies of train/val metrics for the log-scale plots; a legend name per series
    logs = rrd_column(chunks["/metrics_log10/train_loss"], "Scalars:scalars")
    assert np.allclose(np.array(logs), np.log10(np.array(values)), atol=1e-6)
    assert rrd_column(chunks["/metrics/val/pos_err"], "SeriesLines:names") == [["val"]]
    # the summary table holds the latest value of every metric; hparams carry seed, trainer and data
    table = rrd_column(chunks["/summary"], "TextDocument:text")[-1][0]
    assert "| loss | " in table and "| pos_err |  | " in table  # rows: metric, columns: train, val
    hparams = rrd_column(chunks["/hparams"], "TextDocument:text")[-1][0]
    assert all(f'"{k}"' in hparams for k in ("lr", "seed", "trainer", "max_epochs"))
    # batched rows: a few chunks per entity, not one per logged row
    assert max(len(b) for b in chunks.values()) <= 2 and rrd_data_chunks(path) <= 2 * len(chunks)
    # the blueprint: full-range plots grouping the metrics, the scene views, opening at the last step
    # the last layout sent (stores are not ordered): the one plotting the most metrics
    blueprints = RrdReader(path).blueprints()
    latest = max(blueprints, key=lambda bp: sum(len(v.get("query", [])) for v in rrd_views(path, bp).values()))
    views = list(rrd_views(path, latest).values())
    plots = [v for v in views if v["class"] == "TimeSeries"]
    queried = {q for v in plots for q in v["query"]}
    assert {"metrics/train_loss", "metrics_log10/train_loss", "metrics/val/pos_err"} <= queried
    assert all(v["ranges"] == [{"timeline": "step", "range": {"start": None, "end": None}}] for v in plots)
    assert sum(v["class"] == "3D" and v["origin"] == "scene" for v in views) == 2
    panel = rrd_time_panel(path, latest)
    assert panel["TimePanelBlueprint:timeline"] == ["step"] and panel["TimePanelBlueprint:play_state"] == [3]


def test_logger_reused_after_finalize_writes_next_part(tmp_path):
    logger = RerunLogger(save_dir=tmp_path, name="parts", version=3)
    logger.log_metrics({"a": 1.0}, step=0)
    logger.finalize("success")
    logger.log_metrics({"a": torch.tensor(2.0)}, step=1)
    logger.finalize("success")
    first, second = (tmp_path / "parts" / "version_3" / f"{f}.rrd" for f in ("rerun", "rerun_1"))
    for path, value in ((first, 1.0), (second, 2.0)):
        rrd_verify(path)
        assert rrd_column(rrd_chunks(path)["/metrics/a"], "Scalars:scalars") == [[value]]
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
    visual = random_visual()
    log_scene(rec, "ctrl", {"backbone": visual["backbone"], "pose_true": visual["pose_true"]})
    log_path(rec, "ctrl/target", np.zeros((4, 3)), color=(255, 0, 0))
    with pytest.raises(ValueError, match="unknown visual keys"):
        log_scene(rec, "ctrl", {"backbones": visual["backbone"]})
    with pytest.raises(ValueError, match=r"pose_pred.*\(…, 4, 4\)"):
        log_scene(rec, "ctrl", {"pose_pred": torch.eye(3)})
    rec.disconnect()
    rrd_verify(path)
    chunks = rrd_chunks(path)
    assert {"/ctrl/backbone", "/ctrl/tip_true", "/ctrl/target"} <= set(chunks)
    assert "/ctrl/tip_error" not in chunks and "/ctrl/workspace" not in chunks
    assert len(rrd_column(chunks["/ctrl/backbone"], "LineStrips3D:strips")[0]) == K
    vectors = np.array(rrd_column(chunks["/ctrl/tip_true"], "Arrows3D:vectors")[0])
    origins = np.array(rrd_column(chunks["/ctrl/tip_true"], "Arrows3D:origins")[0])
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
        proc = subprocess.Popen([rerun_cli(), "--serve-grpc", "--port", str(port)], stdout=subprocess.DEVNULL,
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
    rrd_verify(tmp_path / "live" / "rerun.rrd")
