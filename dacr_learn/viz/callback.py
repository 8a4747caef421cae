"""Rerun in a Lightning run: the run's context and its 3D scenes, logged by a callback to a
:class:`~dacr_learn.viz.logger.RerunLogger` (the scene helpers: :mod:`dacr_learn.viz.scene`)."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import torch
from lightning.pytorch import Callback, LightningDataModule, LightningModule, Trainer
from lightning.pytorch.utilities.rank_zero import rank_zero_warn
from matplotlib import colormaps

from .layout import SCENE_ROOT, STEP_TIMELINE
from .logger import RerunLogger
from .scene import DEFAULT_ERROR_RANGE, log_scene

__all__ = ["RerunVisualCallback", "find_rerun_logger", "run_info"]


def _plain(value: Any) -> Any:
    """``value`` if it is JSON-like (numbers, strings, dataclasses, lists of those), else ``None``."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, list | tuple):
        items = [_plain(v) for v in value]
        return items if all(i is not None or v is None for i, v in zip(items, value, strict=True)) else None
    return None


def run_info(trainer: Trainer) -> dict[str, Any]:
    """What a run's hparams miss: the global seed, the trainer's settings and the datamodule's (its ``hparams``, else
    its public plain attributes: numbers, strings, dataclasses such as the robot spec, tuples of those)."""
    seed = os.environ.get("PL_GLOBAL_SEED")
    settings = {"max_epochs": trainer.max_epochs, "max_steps": trainer.max_steps, "precision": trainer.precision,
                "accumulate_grad_batches": trainer.accumulate_grad_batches, "world_size": trainer.world_size,
                "gradient_clip_val": trainer.gradient_clip_val, "log_every_n_steps": trainer.log_every_n_steps,
                "strategy": type(trainer.strategy).__name__, "accelerator": type(trainer.accelerator).__name__}
    info: dict[str, Any] = {"seed": None if seed is None else int(seed), "trainer": settings}
    dm = getattr(trainer, "datamodule", None)
    if dm is not None:
        own = set(vars(LightningDataModule()))  # prepare_data_per_node, …: Lightning's, not the data's settings
        mine = {k: _plain(v) for k, v in vars(dm).items() if not k.startswith("_") and k not in own}
        data = dict(dm.hparams) if getattr(dm, "hparams", None) else {k: v for k, v in mine.items() if v is not None}
        info["data"] = {"class": type(dm).__name__, **data}
    return info


def find_rerun_logger(trainer: Trainer) -> RerunLogger | None:
    """The first :class:`RerunLogger` among ``trainer.loggers``, or ``None``."""
    return next((lg for lg in trainer.loggers if isinstance(lg, RerunLogger)), None)


class RerunVisualCallback(Callback):
    """The run's context and 3D scenes for a :class:`RerunLogger`: at fit start :func:`run_info` and the CLI config
    (``pl_module.run_config``); after every ``every_n_epochs``-th validation ``pl_module.visual_batch()`` (the dict of
    :func:`log_scene`, CPU tensors, metres) under ``prefix`` at the global step, at most ``max_workspace_points``
    points on the log scale ``error_range`` [m]. Skipped in the sanity check, on ranks other than 0, without a
    :class:`RerunLogger`, and (with one warning) for a module without ``visual_batch``.
    """

    def __init__(
        self, every_n_epochs: int = 1, prefix: str = SCENE_ROOT, axis_length: float = 0.01,
        cmap: str = "viridis", error_range: tuple[float, float] = DEFAULT_ERROR_RANGE,
        max_workspace_points: int = 1000,
    ) -> None:
        if every_n_epochs < 1:
            raise ValueError(f"every_n_epochs must be >= 1, got {every_n_epochs}")
        if cmap not in colormaps:
            raise ValueError(f"unknown matplotlib colormap {cmap!r}")
        self.every_n_epochs = every_n_epochs
        self.prefix = prefix
        self.axis_length = axis_length
        self.cmap = cmap
        self.error_range = error_range
        self.max_workspace_points = max_workspace_points
        self._warned = False

    def on_fit_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        logger = find_rerun_logger(trainer)
        if logger is None or not trainer.is_global_zero:
            return
        logger.log_hyperparams(run_info(trainer))
        config = getattr(pl_module, "run_config", None)
        if isinstance(config, str):
            logger.log_config(config)

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
        log_scene(rec, self.prefix, visual, axis_length=self.axis_length, cmap=self.cmap,
                  error_range=self.error_range, max_points=self.max_workspace_points)
