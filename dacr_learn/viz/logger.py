"""Rerun logging for Lightning: the logger (its 3D visual callback: :mod:`.callback`; blueprints: :mod:`.layout`;
scene helpers: :mod:`.scene`). What a recording shows: docs/rerun.md.

Everything goes to a dedicated :class:`rerun.RecordingStream` (never the global one), so several loggers,
tests or scripts can log side by side. The scene is in metres. Entity paths::

    metrics/<name>, metrics_log10/<name>   rr.Scalars on the "step" timeline (+ static rr.SeriesLines), log10
    summary, hparams, config               rr.TextDocument: latest metrics table; hparams (JSON); CLI YAML
    scene                                  static rr.ViewCoordinates (right-handed, z up)
    scene/backbone, scene/tip_error        rr.LineStrips3D: ground-truth backbones; true tip -> predicted tip
    scene/tip_true, scene/tip_pred         rr.Arrows3D: true and predicted tip frames
    scene/workspace(/colour_scale)         rr.Points3D coloured by position error (fixed log scale), colour bar
    run/status                             rr.TextLog written by ``finalize``

Rows are batched by the recording's chunk batcher and written when it is flushed (at ``finalize``; every
``live_flush_s`` when streaming to a viewer). Written for rerun-sdk 0.41.
"""

from __future__ import annotations

import json
import math
import os
import sys
import uuid
from argparse import Namespace
from collections.abc import Mapping
from datetime import timedelta
from pathlib import Path
from typing import Any

import rerun as rr
import torch
from lightning.fabric.loggers.logger import rank_zero_experiment
from lightning.fabric.utilities.logger import _convert_params
from lightning.pytorch.loggers import Logger
from lightning.pytorch.utilities.rank_zero import rank_zero_only, rank_zero_warn

from ..runs import free_path
from . import layout
from .layout import default_blueprint, metric_entity
from .scene import DEFAULT_ERROR_RANGE, colour_note, log_frames, log_path, log_scene, log_workspace

__all__ = [
    "RerunLogger", "default_blueprint",
    "log_frames", "log_path", "log_scene", "log_workspace", "metric_entity",
]

STATUS_ENTITY = "run/status"
DEFAULT_GRPC_URL = "rerun+http://127.0.0.1:9876/proxy"
FILE_ONLY_FLUSH = timedelta(hours=1)   # file only: rows accumulate into large chunks until finalize


def _rerun_executable() -> str | None:
    """The ``rerun`` CLI installed next to the running Python, if any (else PATH is searched)."""
    candidate = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    return str(candidate) if candidate.exists() else None


class RerunLogger(Logger):
    """Lightning logger writing metrics and hyper-parameters to a Rerun recording.

    Saved to ``<save_dir>/<name>/rerun.rrd`` (``<save_dir>/<name>/<version>/`` with ``version``; an int becomes
    ``version_<n>``), never over an existing file (the first free of ``rerun.rrd``, ``rerun_1.rrd``, …); ``spawn=True``
    streams to a spawned viewer (port 9876), ``connect`` to a running one; ``save_dir=None`` writes no file. Only
    rank 0 logs; ``.experiment`` / ``.recording`` is the :class:`rerun.RecordingStream`. ``finalize`` closes the sinks
    unless ``close_on_finalize=False`` and the run succeeded (until :meth:`close`); used again, the logger writes the
    next free ``rerun_<k>.rrd`` with the same ``recording_id`` (default a new UUID; a resumed run passes its own).
    ``recording_name``: the viewer's name (default ``name`` or ``name/version``); ``live_flush_s``: how often rows
    are sent when streaming.
    """

    def __init__(
        self, save_dir: str | os.PathLike | None = "runs", name: str = "default",
        version: int | str | None = None, spawn: bool = False, connect: str | None = None,
        application_id: str = "dacr_learn", flush_timeout: float = 10.0, close_on_finalize: bool = True,
        live_flush_s: float = 1.0, recording_id: str | None = None, recording_name: str | None = None,
    ) -> None:
        super().__init__()
        if save_dir is None and not spawn and not connect:
            raise ValueError("RerunLogger needs somewhere to write: save_dir, spawn or connect")
        self._save_dir = None if save_dir is None else os.fspath(save_dir)
        self._name = name
        self._version = version
        self._spawn = spawn
        self._connect = connect
        self._application_id = application_id
        self._flush_timeout = flush_timeout
        self._close_on_finalize = close_on_finalize
        self._recording_id = recording_id or str(uuid.uuid4())
        self._recording_name = recording_name
        self._rec: rr.RecordingStream | None = None
        self._path: str | None = None  # the .rrd file being (or last) written
        self._live_flush = timedelta(seconds=live_flush_s)
        self._metric_names: set[str] = set()
        self._latest: dict[str, tuple[int, float]] = {}  # metric -> (step, value), for the summary table
        self._hparams: dict[str, Any] = {}
        self._config: str | None = None

    @property
    def name(self) -> str:
        return self._name

    @property
    def version(self) -> int | str:
        """The version given, or ``""`` (ModelCheckpoint then saves to ``log_dir/checkpoints``)."""
        return "" if self._version is None else self._version

    @property
    def save_dir(self) -> str | None:
        return self._save_dir

    @property
    def root_dir(self) -> str | None:
        return None if self._save_dir is None else os.path.join(self._save_dir, self._name)

    @property
    def log_dir(self) -> str | None:
        if self.root_dir is None or self._version is None:
            return self.root_dir
        version = self._version if isinstance(self._version, str) else f"version_{self._version}"
        return os.path.join(self.root_dir, version)

    @property
    def rrd_path(self) -> str | None:
        """The ``.rrd`` file being (or last) written (before the first, the one it will write: the first free of
        ``rerun.rrd``, ``rerun_1.rrd``, …, :func:`~dacr_learn.runs.free_path`), or ``None`` without ``save_dir``."""
        if self.log_dir is None:
            return None
        return self._path or str(free_path(self.log_dir, "rerun.rrd"))

    @property
    @rank_zero_experiment
    def experiment(self) -> rr.RecordingStream:
        """The dedicated :class:`rerun.RecordingStream` (opened on first use, rank 0 only)."""
        if self._rec is None:
            self._rec = self._open()
        return self._rec

    @property
    def recording(self) -> rr.RecordingStream:
        """Alias of :attr:`experiment`."""
        return self.experiment

    def _sinks(self, rec: rr.RecordingStream) -> list[Any]:
        sinks: list[Any] = []
        if self.rrd_path is not None:
            Path(self.rrd_path).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(self.rrd_path))
        urls = []
        if self._spawn:
            rr.spawn(connect=False, executable_path=_rerun_executable(), recording=rec)
            urls.append(DEFAULT_GRPC_URL)
        if self._connect and self._connect not in urls:
            urls.append(self._connect)
        return sinks + [rr.GrpcSink(url) for url in urls]

    def _open(self) -> rr.RecordingStream:
        self._path = None
        self._path = self.rrd_path                                   # a new part, next to the one written before
        live = self._spawn or bool(self._connect)
        batching = rr.ChunkBatcherConfig(flush_tick=self._live_flush if live else FILE_ONLY_FLUSH,
                                         flush_num_bytes=8 << 20, flush_num_rows=1 << 20)
        rec = rr.RecordingStream(self._application_id, recording_id=self._recording_id, batcher_config=batching)
        rec.set_sinks(*self._sinks(rec), default_blueprint=self._blueprint())
        run = self._name if self._version is None else f"{self._name}/{self._version}"
        rec.send_recording_name(self._recording_name or run)
        rec.log(layout.SCENE_ROOT, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name in self._metric_names:
            self._log_series_style(rec, name)
        if self._hparams:
            self._log_hparams(rec)
        if self._config is not None:
            self._log_config(rec)
        return rec

    def _blueprint(self):
        return default_blueprint(self._metric_names, colour_note=colour_note(DEFAULT_ERROR_RANGE))

    def _flush(self, rec: rr.RecordingStream, timeout: float) -> None:
        try:
            rec.flush(timeout_sec=timeout)
        except RuntimeError as err:  # e.g. the viewer is gone; the file sink is unaffected
            rank_zero_warn(f"RerunLogger: could not flush to every sink: {err}")

    @rank_zero_only
    def save(self) -> None:
        """Nothing: Lightning calls this after every ``log_metrics``, and flushing there wrote one
        chunk per row. The batcher sends rows on its own tick when streaming; files at finalize."""

    @rank_zero_only
    def finalize(self, status: str) -> None:
        """Flush and close every sink so the ``.rrd`` file is complete (with ``close_on_finalize=False`` a successful
        stage only flushes; call :meth:`close`)."""
        if self._rec is None:
            return
        if status == "success" and not self._close_on_finalize:
            self._flush(self._rec, self._flush_timeout)
            return
        self.close(status)

    @rank_zero_only
    def close(self, status: str = "success") -> None:
        """Write the run status, flush and disconnect: the ``.rrd`` file is complete after this."""
        if self._rec is None:
            return
        rec, self._rec = self._rec, None
        rec.log(STATUS_ENTITY, rr.TextLog(f"run {status}", level="INFO"))
        self._flush(rec, self._flush_timeout)
        rec.disconnect()

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log each metric as rr.Scalars at ``metrics/<name>`` and ``step``; train/val metrics also as log10 at
        ``metrics_log10/<name>`` (positive values only); test metrics and others update the summary table only."""
        rec = self.experiment
        new = set(metrics) - self._metric_names
        if new:  # plots are grouped by quantity: refresh the layout when new names appear
            groups = layout.metric_groups(self._metric_names)
            self._metric_names |= new
            for name in new:
                self._log_series_style(rec, name)
            if layout.metric_groups(self._metric_names) != groups:
                rec.send_blueprint(self._blueprint())
        if step is not None:
            rec.set_time(layout.STEP_TIMELINE, sequence=int(step))
        at = int(step) if step is not None else max((s for s, _ in self._latest.values()), default=0)
        for name, value in metrics.items():
            value = float(value.item() if isinstance(value, torch.Tensor) else value)
            rec.log(metric_entity(name), rr.Scalars(value))
            if layout.is_plotted(name) and value > 0 and math.isfinite(value):
                rec.log(layout.log10_entity(name), rr.Scalars(math.log10(value)))
            self._latest[name] = (at, value)
        if any(not name.startswith("train") and name != "epoch" for name in metrics):  # eval/test: refresh the table
            summary = rr.TextDocument(layout.summary_markdown(self._latest), media_type="text/markdown")
            rec.log(layout.SUMMARY_ENTITY, summary)

    def _log_series_style(self, rec: rr.RecordingStream, name: str) -> None:
        label, color = layout.series_style(name)
        style = rr.SeriesLines(names=[label], colors=[color], widths=[1.5])
        rec.log(metric_entity(name), style, static=True)
        if layout.is_plotted(name):
            rec.log(layout.log10_entity(name), rr.SeriesLines(names=[label], colors=[color], widths=[1.5]), static=True)

    @rank_zero_only
    def log_hyperparams(self, params: dict[str, Any] | Namespace, *args: Any, **kw: Any) -> None:
        """Record hyper-parameters (merged over calls) as a static JSON rr.TextDocument."""
        self._hparams.update(_convert_params(params) or {})
        self._log_hparams(self.experiment)

    @rank_zero_only
    def log_config(self, text: str) -> None:
        """Record the run's full configuration (e.g. the CLI's YAML) as a static rr.TextDocument."""
        self._config = text
        self._log_config(self.experiment)

    def _log_config(self, rec: rr.RecordingStream) -> None:
        doc = rr.TextDocument(f"```yaml\n{self._config}\n```", media_type="text/markdown")
        rec.log(layout.CONFIG_ENTITY, doc, static=True)

    def _log_hparams(self, rec: rr.RecordingStream) -> None:
        try:
            text = json.dumps(self._hparams, indent=2, default=repr)
        except (TypeError, ValueError):  # e.g. non-string keys
            text = repr(self._hparams)
        doc = rr.TextDocument(f"```json\n{text}\n```", media_type="text/markdown")
        rec.log(layout.HPARAMS_ENTITY, doc, static=True)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_rec"] = None  # a RecordingStream cannot be pickled; reopened on demand
        return state
