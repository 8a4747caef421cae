"""Rerun logging for Lightning: a logger and a 3D visual callback (scene helpers: rerun_scene).

Everything goes to a dedicated :class:`rerun.RecordingStream` (never the global one), so
several loggers, tests or scripts can log side by side. The scene is in metres.

Layout of a recording (entity paths)::

    metrics/<name>           rr.Scalars on the "step" sequence timeline
    hparams                  rr.TextDocument (static, JSON)
    scene                    static rr.ViewCoordinates (right-handed, z up)
    scene/backbone           rr.LineStrips3D, ground-truth backbone curves
    scene/tip_true           rr.Arrows3D, ground-truth tip frames (saturated x/y/z colours)
    scene/tip_pred           rr.Arrows3D, predicted tip frames (lighter colours)
    scene/tip_error          rr.LineStrips3D, segments true tip -> predicted tip
    scene/workspace          rr.Points3D coloured by position error + rr.TextLog summary
    run/status               rr.TextLog written by ``finalize``

Open a run with ``.venv/bin/rerun runs/<name>/rerun.rrd``. Written for rerun-sdk 0.41
(``rr.set_time(..., sequence=)``, ``rr.Scalars``, sinks via ``set_sinks``).
"""

from __future__ import annotations

import json
import os
import sys
import uuid
from argparse import Namespace
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import rerun as rr
import rerun.blueprint as rrb
import torch
from lightning.fabric.loggers.logger import rank_zero_experiment
from lightning.fabric.utilities.logger import _convert_params
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.loggers import Logger
from lightning.pytorch.utilities.rank_zero import rank_zero_only, rank_zero_warn
from matplotlib import colormaps

from .rerun_scene import log_frames, log_path, log_scene, log_workspace  # noqa: E402,F401  (re-exported)

__all__ = [
    "RerunLogger", "RerunVisualCallback", "default_blueprint", "find_rerun_logger",
    "log_frames", "log_path", "log_scene", "log_workspace", "metric_entity",
]

STEP_TIMELINE = "step"
METRICS_ROOT = "metrics"
HPARAMS_ENTITY = "hparams"
SCENE_ROOT = "scene"
STATUS_ENTITY = "run/status"
DEFAULT_GRPC_URL = "rerun+http://127.0.0.1:9876/proxy"


def _rerun_executable() -> str | None:
    """The ``rerun`` CLI installed next to the running Python, if any (else PATH is searched)."""
    candidate = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    return str(candidate) if candidate.exists() else None


def metric_entity(name: str) -> str:
    """Entity path of a metric: ``"val/pos_err"`` -> ``"metrics/val/pos_err"`` (parts escaped)."""
    parts = [rr.escape_entity_path_part(p) for p in str(name).split("/") if p]
    return "/".join([METRICS_ROOT, *parts])


def default_blueprint(metric_names: Iterable[str] = ()) -> rrb.Blueprint:
    """Default layout: the 3D scene and a text log beside a grid of one plot per metric.

    With no ``metric_names`` the grid holds a single plot of everything under ``metrics/``.
    """
    names = sorted(set(metric_names))
    plots = [rrb.TimeSeriesView(origin=metric_entity(n), name=n) for n in names]
    plots = plots or [rrb.TimeSeriesView(origin=METRICS_ROOT, name="metrics")]
    scene_3d = rrb.Spatial3DView(origin=SCENE_ROOT, name="scene")
    scene = rrb.Vertical(scene_3d, rrb.TextLogView(origin="/", name="log"), row_shares=[4, 1])
    hparams = rrb.TextDocumentView(origin=HPARAMS_ENTITY, name="hparams")
    side = rrb.Tabs(rrb.Grid(*plots, name="metrics"), hparams)
    return rrb.Blueprint(rrb.Horizontal(scene, side, column_shares=[3, 2]))


class RerunLogger(Logger):
    """Lightning logger writing metrics and hyper-parameters to a Rerun recording.

    The recording is saved to ``<save_dir>/<name>/rerun.rrd`` (``<save_dir>/<name>/<version>/``
    when ``version`` is given; an int becomes ``version_<n>``), optionally streamed to a
    spawned viewer (``spawn=True``, port 9876) and/or a running one
    (``connect="rerun+http://host:9876/proxy"``).
    ``save_dir=None`` writes no file. Metrics go to ``metrics/<name>`` on the ``step`` timeline.
    Only rank 0 logs; ``.experiment`` / ``.recording`` is the :class:`rerun.RecordingStream`.

    ``finalize`` flushes and closes all sinks, so the file is complete — unless
    ``close_on_finalize=False`` and the run succeeded: then the recording stays open (one file
    across ``fit`` and a following ``test``) until :meth:`close` is called. If the logger is used
    again afterwards (``trainer.fit`` then ``trainer.test``) the next part goes to
    ``rerun_1.rrd``, ``rerun_2.rrd``, … with the same recording id: open them together and
    the viewer merges them into one recording.
    """

    def __init__(
        self, save_dir: str | os.PathLike | None = "runs", name: str = "default",
        version: int | str | None = None, spawn: bool = False, connect: str | None = None,
        application_id: str = "dacr_learn", flush_timeout: float = 10.0, close_on_finalize: bool = True,
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
        self._recording_id = str(uuid.uuid4())
        self._rec: rr.RecordingStream | None = None
        self._part = -1  # index of the .rrd part being (or last) written
        self._metric_names: set[str] = set()
        self._hparams: dict[str, Any] = {}


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
        """The ``.rrd`` file being (or last) written, or ``None`` without ``save_dir``."""
        if self.log_dir is None:
            return None
        part = max(self._part, 0)
        return os.path.join(self.log_dir, "rerun.rrd" if part == 0 else f"rerun_{part}.rrd")

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
        self._part += 1
        rec = rr.RecordingStream(self._application_id, recording_id=self._recording_id)
        rec.set_sinks(*self._sinks(rec), default_blueprint=default_blueprint(self._metric_names))
        run = self._name if self._version is None else f"{self._name}/{self._version}"
        rec.send_recording_name(run)
        rec.log(SCENE_ROOT, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if self._hparams:
            self._log_hparams(rec)
        return rec

    def _flush(self, rec: rr.RecordingStream, timeout: float) -> None:
        try:
            rec.flush(timeout_sec=timeout)
        except RuntimeError as err:  # e.g. the viewer is gone; the file sink is unaffected
            rank_zero_warn(f"RerunLogger: could not flush to every sink: {err}")

    @rank_zero_only
    def save(self) -> None:
        """Start flushing buffered data (does not wait)."""
        if self._rec is not None:
            self._flush(self._rec, 0.0)

    @rank_zero_only
    def finalize(self, status: str) -> None:
        """Flush and close every sink so the ``.rrd`` file is complete and readable.

        With ``close_on_finalize=False`` a successful stage only flushes; call :meth:`close`.
        """
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
        """Log each metric as rr.Scalars under ``metrics/<name>`` at ``step``."""
        rec = self.experiment
        new = set(metrics) - self._metric_names
        if new:  # one plot per metric: refresh the layout when new names appear
            self._metric_names |= new
            rec.send_blueprint(default_blueprint(self._metric_names))
        if step is not None:
            rec.set_time(STEP_TIMELINE, sequence=int(step))
        for name, value in metrics.items():
            value = value.item() if isinstance(value, torch.Tensor) else value
            rec.log(metric_entity(name), rr.Scalars(float(value)))

    @rank_zero_only
    def log_hyperparams(self, params: dict[str, Any] | Namespace, *args: Any, **kw: Any) -> None:
        """Record hyper-parameters (merged over calls) as a static JSON rr.TextDocument."""
        self._hparams.update(_convert_params(params) or {})
        self._log_hparams(self.experiment)

    def _log_hparams(self, rec: rr.RecordingStream) -> None:
        try:
            text = json.dumps(self._hparams, indent=2, default=repr)
        except (TypeError, ValueError):  # e.g. non-string keys
            text = repr(self._hparams)
        doc = rr.TextDocument(f"```json\n{text}\n```", media_type="text/markdown")
        rec.log(HPARAMS_ENTITY, doc, static=True)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_rec"] = None  # a RecordingStream cannot be pickled; reopened on demand
        return state


def find_rerun_logger(trainer: Trainer) -> RerunLogger | None:
    """The first :class:`RerunLogger` among ``trainer.loggers``, or ``None``."""
    return next((lg for lg in trainer.loggers if isinstance(lg, RerunLogger)), None)


class RerunVisualCallback(Callback):
    """At the end of every ``every_n_epochs``-th validation, log ``pl_module.visual_batch()``.

    ``visual_batch()`` returns the dict described in :func:`log_scene` (CPU tensors, metres);
    it is logged under ``prefix`` at the trainer's global step. Skipped during the sanity
    check, on ranks other than 0, without a :class:`RerunLogger` among the trainer's loggers,
    and (with one warning) when the module has no ``visual_batch``.
    """

    def __init__(
        self, every_n_epochs: int = 1, prefix: str = SCENE_ROOT, axis_length: float = 0.01,
        cmap: str = "viridis",
    ) -> None:
        if every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1, got {every_n_epochs}")
        if cmap not in colormaps:
            raise ValueError(f"unknown matplotlib colormap {cmap!r}")
        self.every_n_epochs = every_n_epochs
        self.prefix = prefix
        self.axis_length = axis_length
        self.cmap = cmap
        self._warned = False

    def _due(self, trainer: Trainer) -> bool:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return False
        return (trainer.current_epoch + 1) % self.every_n_epochs == 0

    def on_validation_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        logger = find_rerun_logger(trainer)
        if logger is None or not self._due(trainer):
            return
        visual_batch = getattr(pl_module, "visual_batch", None)
        if not callable(visual_batch):
            if not self._warned:
                name = type(pl_module).__name__
                rank_zero_warn(f"RerunVisualCallback: {name} has no visual_batch(); nothing logged")
                self._warned = True
            return
        with torch.no_grad():
            visual = visual_batch()
        rec = logger.experiment
        rec.set_time(STEP_TIMELINE, sequence=trainer.global_step)
        log_scene(rec, self.prefix, visual, axis_length=self.axis_length, cmap=self.cmap)
