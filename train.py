"""Train and evaluate learned FK / IK models from YAML configs (LightningCLI).

    python train.py fit  --config configs/default.yaml          # train, then test → runs/default/
    python train.py fit  --config configs/default.yaml --ckpt_path last   # resume an interrupted run
    python train.py test --config configs/default.yaml --ckpt_path runs/default/checkpoints/last.ckpt
    python train.py fit  --config configs/default.yaml --print_config
    python train.py fit  --config configs/fk_tdcr3.yaml --trainer.devices 2 --trainer.strategy ddp

Every run writes to runs/<run_name>/: checkpoints/ (last.ckpt is refreshed every epoch and on
interruption), rerun.rrd (metrics and 3D scenes), metrics.json (test-split summary).
"""
from __future__ import annotations

import atexit
import json
import time
from pathlib import Path

import torch
from lightning.pytorch.callbacks import ModelCheckpoint, OnExceptionCheckpoint
from lightning.pytorch.cli import LightningCLI, SaveConfigCallback

from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.metrics import format_table
from dacr_learn.rerun_log import RerunLogger, RerunVisualCallback
from dacr_learn.training import KinematicsModule


class InterruptCheckpoint(OnExceptionCheckpoint):
    """Saves ``last.ckpt`` when a run is interrupted (Ctrl-C, error) and, unlike its parent,
    keeps it at teardown, so ``fit --ckpt_path last`` resumes from the point of interruption."""

    def teardown(self, trainer, *args, **kwargs) -> None:
        pass


class SaveConfigToRunDir(SaveConfigCallback):
    """Writes config.yaml into the run's own directory (trainer.default_root_dir = runs/<run_name>);
    Lightning's default uses the logger's save_dir, which every run shares."""

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self.already_saved:
            return
        if trainer.is_global_zero:
            path = Path(trainer.default_root_dir) / self.config_filename
            path.parent.mkdir(parents=True, exist_ok=True)
            self.parser.save(self.config, path, skip_none=False, overwrite=True, multifile=self.multifile)
        self.already_saved = trainer.strategy.broadcast(True)


class DacrCLI(LightningCLI):
    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument("--run_name", type=str, default="default", help="outputs go to <runs_dir>/<run_name>/")
        parser.add_argument("--runs_dir", type=str, default="runs")
        parser.add_argument("--rerun_spawn", type=bool, default=False, help="also stream to a spawned Rerun viewer")
        parser.add_argument("--rerun_connect", type=str | None, default=None, help="URL of a running Rerun viewer")
        parser.add_argument("--num_threads", type=int, default=1,
                            help="torch intra-op threads; 1 is fastest for these small MLPs on CPU")
        parser.link_arguments("data.robot", "model.init_args.robot")

    def before_instantiate_classes(self) -> None:
        torch.set_num_threads(self.run_config.num_threads)

    @property
    def run_config(self):
        return self.config[self.subcommand] if self.subcommand else self.config

    @property
    def run_dir(self) -> Path:
        return Path(self.run_config.runs_dir) / self.run_config.run_name

    def instantiate_trainer(self, **kwargs):
        cfg, ckpt_dir = self.run_config, self.run_dir / "checkpoints"
        configured = self._get(self.config_init, "trainer", default={})
        callbacks = list(configured.get("callbacks") or []) + [
            ModelCheckpoint(dirpath=ckpt_dir, filename="epoch{epoch:03d}", auto_insert_metric_name=False,
                            save_last=True, save_top_k=1),
            InterruptCheckpoint(dirpath=ckpt_dir, filename="last"),
            RerunVisualCallback()]
        logger = RerunLogger(save_dir=cfg.runs_dir, name=cfg.run_name, spawn=cfg.rerun_spawn,
                             connect=cfg.rerun_connect, close_on_finalize=False)   # one file for fit + test
        atexit.register(logger.close)
        kwargs = {"default_root_dir": str(self.run_dir), "logger": logger, "callbacks": callbacks, **kwargs}
        return super().instantiate_trainer(**kwargs)

    def before_fit(self) -> None:
        self._fit_started = time.perf_counter()
        self.model.run_config = self.parser.dump(self.config, skip_none=False)   # carried by checkpoints

    def after_fit(self) -> None:
        seconds = time.perf_counter() - self._fit_started
        if not self.trainer.interrupted:
            self.trainer.test(self.model, datamodule=self.datamodule, verbose=False)
            self._write_summary(train_seconds=seconds)
        self.trainer.logger.close()

    def after_test(self) -> None:
        self._write_summary()
        self.trainer.logger.close()

    def _write_summary(self, **extra) -> None:
        if not self.trainer.is_global_zero:
            return
        model: KinematicsModule = self.model
        h = model.hparams
        summary = {**model.test_summary, **extra, "task": type(model).__name__.removesuffix("Module").lower(),
                   "features": h.features, "robot": model.spec.name, "n_test": len(self.datamodule.splits["test"]["q"])}
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "metrics.json").write_text(json.dumps(summary, indent=2))
        print(format_table(model.test_summary, f"\nTest metrics of {summary['task'].upper()} ({h.features} features, "
                                               f"robot {model.spec.name}) → {self.run_dir / 'metrics.json'}"))
        rrd = self.run_dir / "rerun.rrd"
        print(f"  Rerun recording: {rrd}  (open with: .venv/bin/rerun {rrd})")


def main(args=None, run: bool = True) -> DacrCLI:
    """Run the CLI on ``args`` (default: sys.argv); ``run=False`` only instantiates (no subcommand)."""
    return DacrCLI(KinematicsModule, KinematicsDataModule, subclass_mode_model=True,
                   save_config_callback=SaveConfigToRunDir, args=args, run=run)


if __name__ == "__main__":
    main()
