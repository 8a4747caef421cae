"""Train and evaluate learned FK / IK models from YAML configs (LightningCLI).

    python train.py fit  --config configs/default.yaml          # a new run → runs/default/version_<n>/
    python train.py fit  --config configs/default.yaml --ckpt_path last   # resume the newest run of that name
    python train.py test --config configs/default.yaml --ckpt_path last   # → runs/default/version_<n>/test_<k>/
    python train.py fit  --config configs/default.yaml --print_config
    python train.py fit  --config configs/fk_tdcr3.yaml --trainer.devices 2 --trainer.strategy ddp

A ``fit`` without ``--ckpt_path`` always starts a new run folder ``<runs_dir>/<run_name>/version_<n>/``;
nothing a run writes overwrites another run (layout: :mod:`dacr_learn.runs`). ``--ckpt_path`` takes
``last`` (the newest version of ``--run_name`` that has a ``last.ckpt``) or a checkpoint file; a resumed
fit continues that run's folder and adds a further ``rerun_<k>.rrd`` part to its recording.
"""
from __future__ import annotations

import atexit
import json
import logging
import os
import re
import shlex
import sys
import time
import warnings
from pathlib import Path

import torch
from lightning.pytorch import Callback
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI, SaveConfigCallback
from lightning.pytorch.utilities.exceptions import SIGTERMException

from dacr_learn import runs
from dacr_learn.checks import load_torch_file
from dacr_learn.console import run_cli
from dacr_learn.data.cosserat import cc_baseline
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.metrics import format_table
from dacr_learn.training import FKModule, KinematicsModule
from dacr_learn.viz.callback import RerunVisualCallback
from dacr_learn.viz.logger import RerunLogger


def quiet_run_handling_warnings() -> None:
    """Lightning warnings about situations this CLI creates on purpose, which a user cannot act on."""
    for message in (
        # a resumed fit writes into its own run folder, which holds that run's checkpoints
        r"Checkpoint directory .* exists and is not empty",
        # Ctrl-C / SIGTERM save mid-epoch; the resumed epoch draws a fresh shuffle of the remaining batches
        r"You're resuming from a checkpoint that ended before the epoch ended",
        # `test` restores weights only; the ModelCheckpoint that wrote the file is a fit-time callback
        r"Be aware that when using `ckpt_path`, callbacks used to create the checkpoint",
    ):
        warnings.filterwarnings("ignore", message=message)


class DropLightningChatter(logging.Filter):
    """Drops Lightning's start-up INFO lines that tell a user of train.py nothing to act on (the seed is in
    config.yaml and the recording; the device is the config's ``trainer.accelerator``)."""

    CHATTER = re.compile(r"(\[rank: \d+\] )?(Seed set to |GPU available: |TPU available: |HPU available: |"
                         r"Loading `train_dataloader` to estimate number of stepping batches)")

    def filter(self, record: logging.LogRecord) -> bool:
        return not self.CHATTER.match(record.getMessage())


def quiet_lightning_chatter() -> None:
    for name in ("lightning.fabric.utilities.seed", "lightning.pytorch.utilities.rank_zero"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, DropLightningChatter) for f in logger.filters):
            logger.addFilter(DropLightningChatter())


class InterruptCheckpoint(Callback):
    """Saves ``last.ckpt`` when a fit stops on an exception (Ctrl-C, SIGTERM, an error) after its first
    training step and prints the exact command that resumes it.

    Not Lightning's ``OnExceptionCheckpoint``: with one of those among the callbacks, ``fit`` without a
    ``ckpt_path`` silently resumes from ``last`` (Lightning 2.6), which is how a second run used to
    continue the first one instead of starting anew."""

    def __init__(self, dirpath: Path, resume_command: str) -> None:
        self.ckpt_path = str(Path(dirpath) / "last.ckpt")
        self.resume_command = resume_command

    stopped_by: type[BaseException] | None = None   # the exception type that stopped the last fit, if any

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        InterruptCheckpoint.stopped_by = type(exception)
        if trainer.global_step == 0:
            # stopped before the first step (a bad config, Ctrl-C during set-up; in a resumed fit: before its
            # checkpoint was restored): nothing to keep, and saving would replace a resumed run's last.ckpt
            # with untrained weights
            return
        trainer.save_checkpoint(self.ckpt_path, weights_only=False)   # a full state: fit resumes from it
        if trainer.is_global_zero:
            what = {KeyboardInterrupt: "interrupted (Ctrl-C)", SIGTERMException: "stopped by SIGTERM"}.get(
                type(exception), f"stopped by {type(exception).__name__}")
            print(f"\nTraining {what} at epoch {trainer.current_epoch}, step {trainer.global_step}; "
                  f"saved {self.ckpt_path}.\nResume this run with:\n  {self.resume_command}\n",
                  file=sys.stderr, flush=True)


class SaveConfigToRunDir(SaveConfigCallback):
    """Writes config.yaml into the run's own folder (trainer.default_root_dir); Lightning's default
    uses the logger's save_dir, which every run shares. Never overwrites: a resumed fit keeps the
    first config.yaml and writes config_<k>.yaml beside it."""

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self.already_saved:
            return
        if trainer.is_global_zero:
            folder = Path(trainer.default_root_dir)
            folder.mkdir(parents=True, exist_ok=True)
            path = runs.free_path(folder, self.config_filename)
            self.parser.save(self.config, path, skip_unset=False, multifile=self.multifile)
        self.already_saved = trainer.strategy.broadcast(True)


def launched_rank() -> int:
    """Rank of this process when Lightning's DDP launcher (or torchrun) started it, else 0: worker processes
    re-run this script after rank 0 has created the run folders, and must not create their own."""
    return max(int(os.environ.get(name, "0") or 0) for name in ("LOCAL_RANK", "NODE_RANK", "RANK"))


# Rank 0 names the folders it made in its environment, which Lightning's DDP launcher copies to the worker
# processes it starts: a worker uses exactly these, never "the newest version" (another job of the same run
# name may have made a newer one in between).
RUN_FOLDER_ENV, OUT_FOLDER_ENV = "DACR_RUN_FOLDER", "DACR_OUT_FOLDER"


def worker_folders(run_root: Path, subcommand: str | None, ckpt_run: Path | None,
                   environ=os.environ) -> tuple[Path, Path]:
    """(run folder, output folder) of a DDP worker process: the ones rank 0 put in ``environ``
    (:data:`RUN_FOLDER_ENV`, :data:`OUT_FOLDER_ENV`). Without them (a launcher that does not start the workers
    from rank 0) the run of the checkpoint, else the newest version of ``run_root``, and its newest
    ``<subcommand>_<k>`` folder for test/validate/predict."""
    if environ.get(RUN_FOLDER_ENV) and environ.get(OUT_FOLDER_ENV):
        return Path(environ[RUN_FOLDER_ENV]), Path(environ[OUT_FOLDER_ENV])
    run = ckpt_run if ckpt_run is not None else runs.versions(run_root)[-1]
    out = run if subcommand in (None, "fit") else runs.numbered(run, f"{subcommand}_")[-1]
    return run, out


class DacrCLI(LightningCLI):
    def __init__(self, *args, argv: list[str] | None = None, **kwargs) -> None:
        self._argv = list(sys.argv[1:] if argv is None else argv)
        super().__init__(*args, args=argv, **kwargs)

    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument("--run_name", type=str, default="default",
                            help="runs go to <runs_dir>/<run_name>/version_<n>/")
        parser.add_argument("--runs_dir", type=str, default="runs")
        parser.add_argument("--rerun_spawn", type=bool, default=False, help="also stream to a spawned Rerun viewer")
        parser.add_argument("--rerun_connect", type=str | None, default=None, help="URL of a running Rerun viewer")
        parser.add_argument("--num_threads", type=int, default=1,
                            help="torch intra-op threads; 1 is fastest for these small MLPs on CPU")
        parser.link_arguments("data.robot", "model.init_args.robot")

    def before_instantiate_classes(self) -> None:
        quiet_run_handling_warnings()
        torch.set_num_threads(self.run_config.num_threads)
        if self.subcommand is None:   # main(run=False): instantiate only, as for a new fit
            return
        cfg = self.run_config
        ckpt = cfg.get("ckpt_path")
        if self.subcommand in ("test", "validate", "predict") and ckpt is None:
            raise ValueError(f"train.py {self.subcommand} needs --ckpt_path: 'last' (the newest run of "
                             f"--run_name {cfg.run_name!r}) or a checkpoint file such as "
                             f"{self.run_root}/version_0/checkpoints/last.ckpt")
        if ckpt == "last":
            try:
                ckpt = str(runs.find_checkpoint(self.run_root))
            except FileNotFoundError as err:
                raise ValueError(f"--ckpt_path last: {err}") from None
        elif ckpt is not None and not Path(ckpt).is_file():
            raise ValueError(f"--ckpt_path {ckpt}: no such file; expected 'last' or a checkpoint file "
                             f"(e.g. {self.run_root}/version_0/checkpoints/last.ckpt)")
        cfg.ckpt_path = ckpt
        if "verbose" in cfg:   # `test` prints the project's metrics table (after_test); Lightning's repeats it
            cfg.verbose = False

    @property
    def run_config(self):
        return self.config[self.subcommand] if self.subcommand else self.config

    @property
    def run_root(self) -> Path:
        """``<runs_dir>/<run_name>``: the folder holding this run name's versions."""
        return Path(self.run_config.runs_dir) / self.run_config.run_name

    def _run_folders(self) -> tuple[Path, Path, dict]:
        """(run folder, folder this command writes to, run info) — creating a new folder where needed."""
        ckpt = self.run_config.get("ckpt_path")
        run = runs.checkpoint_run_dir(ckpt) if ckpt is not None else None
        if launched_rank() > 0:   # a DDP worker process: rank 0 made this command's folders before launching it
            run, out = worker_folders(self.run_root, self.subcommand, run)
            info = runs.read_run_info(run) if self.subcommand in (None, "fit") else {"recording_id": None}
            return run, out, info
        run, out, info = self._new_run_folders(ckpt, run)
        os.environ[RUN_FOLDER_ENV], os.environ[OUT_FOLDER_ENV] = str(run.resolve()), str(out.resolve())
        return run, out, info

    def _new_run_folders(self, ckpt, run: Path | None) -> tuple[Path, Path, dict]:
        """Rank 0's part of :meth:`_run_folders`."""
        if self.subcommand in (None, "fit"):
            if run is None:   # a new run (or fine-tuning from a checkpoint outside any run folder)
                run = runs.new_numbered_dir(self.run_root, "version_")
                info = runs.write_run_info(run, run_name=self.run_config.run_name, version=run.name,
                                           started_from=ckpt)
            else:
                info = runs.read_run_info(run)
            return run, run, info
        if run is None:
            run = runs.new_numbered_dir(self.run_root, "version_")
            runs.write_run_info(run, run_name=self.run_config.run_name, version=run.name, evaluates=ckpt)
        out = runs.new_numbered_dir(run, f"{self.subcommand}_")
        return run, out, {"recording_id": None}

    def _resume_command(self, ckpt: Path) -> str:
        args, skip = [], False
        for arg in self._argv:
            if skip:
                skip = False
            elif arg == "--ckpt_path":
                skip = True
            elif not arg.startswith("--ckpt_path="):
                args.append(arg)
        python = Path(sys.executable)
        try:
            python = python.relative_to(Path.cwd())
        except ValueError:
            pass
        return shlex.join([str(python), "train.py", *args, "--ckpt_path", str(ckpt)])

    def instantiate_trainer(self, **kwargs):
        cfg = self.run_config
        if cfg.get("ckpt_path") is not None:
            blob = load_torch_file(cfg.ckpt_path, runs.CHECKPOINT)
            runs.check_checkpoint_fits(cfg.ckpt_path, blob, type(self.model).__name__, dict(self.model.hparams),
                                       self.model.state_dict())
            if self.subcommand == "fit":
                runs.check_same_schedule(cfg.ckpt_path, blob, cfg.as_dict())
        run, out, info = self._run_folders()
        self.run_dir, self.out_dir = run, out
        ckpt_dir = run / "checkpoints"
        configured = self._get(self.config_init, "trainer", default={})
        callbacks = list(configured.get("callbacks") or []) + [RerunVisualCallback()]
        if self.subcommand in (None, "fit"):
            callbacks += [ModelCheckpoint(dirpath=ckpt_dir, filename="epoch{epoch:03d}", auto_insert_metric_name=False,
                                          save_last=True, save_top_k=1),
                          InterruptCheckpoint(ckpt_dir, self._resume_command(ckpt_dir / "last.ckpt"))]
        name = f"{cfg.run_name}/{run.name}" + ("" if out == run else f"/{out.name}")
        logger = RerunLogger(save_dir=str(out.parent), name=out.name, spawn=cfg.rerun_spawn,
                             connect=cfg.rerun_connect, close_on_finalize=False,   # one file for fit + test
                             recording_id=info.get("recording_id"), recording_name=name)
        atexit.register(logger.close)
        kwargs = {"default_root_dir": str(out), "logger": logger, "callbacks": callbacks,
                  "enable_checkpointing": self.subcommand in (None, "fit"), **kwargs}
        return super().instantiate_trainer(**kwargs)

    def before_fit(self) -> None:
        self._fit_started = time.perf_counter()
        self.model.run_config = self.parser.dump(self.config, skip_unset=False)   # carried by checkpoints

    def after_fit(self) -> None:
        seconds = time.perf_counter() - self._fit_started
        if not self.trainer.interrupted:
            self.trainer.test(self.model, datamodule=self.datamodule, verbose=False)
            self._write_summary(train_seconds=seconds)
        self.trainer.logger.close()

    def after_test(self) -> None:
        self._write_summary(checkpoint=str(self.run_config.ckpt_path))
        self.trainer.logger.close()

    def _write_summary(self, **extra) -> None:
        if not self.trainer.is_global_zero:
            return
        model: KinematicsModule = self.model
        h = model.hparams
        test = self.datamodule.splits["test"]
        summary = {**model.test_summary, **extra, "task": type(model).__name__.removesuffix("Module").lower(),
                   "features": h.features, "robot": model.spec.name, "n_test": len(test["q"])}
        if getattr(self.datamodule, "source", "cc") != "cc" and isinstance(model, FKModule):
            # the analytic CC model on the same split, from the Clarke features of the same joint lengths
            summary["source"] = self.datamodule.source
            summary.update(cc_baseline(model.spec, test["q"], test["pose"]))
        path = runs.free_path(self.out_dir, "metrics.json")   # a resumed fit keeps the first summary too
        path.write_text(json.dumps(summary, indent=2))
        shown = {**model.test_summary, **{k: v for k, v in summary.items() if k.startswith("cc_")}}
        print(format_table(shown, f"\nTest metrics of {summary['task'].upper()} ({h.features} features, "
                                               f"robot {model.spec.name}) → {path}"))
        parts = sorted(self.out_dir.glob("rerun*.rrd"))
        target = parts[0] if len(parts) == 1 else self.out_dir / "*.rrd"
        print(f"  Rerun recording: {target}  (open with: .venv/bin/rerun {target})")


def main(args: list[str] | None = None, run: bool = True) -> DacrCLI:
    """Run the CLI on ``args`` (default: sys.argv); ``run=False`` only instantiates (no subcommand)."""
    return DacrCLI(KinematicsModule, KinematicsDataModule, subclass_mode_model=True,
                   save_config_callback=SaveConfigToRunDir, argv=args, run=run)


def train_command(argv: list[str] | None = None) -> None:
    """:func:`main` as a command: SIGTERM exits with 143 and Ctrl-C with 130 (Lightning exits with 1 after
    the interrupted fit printed how to resume it)."""
    try:
        main(argv)
    except SIGTERMException:
        raise SystemExit(143) from None
    except SystemExit:
        if InterruptCheckpoint.stopped_by is KeyboardInterrupt:
            raise SystemExit(130) from None
        raise


def run_command_line(argv: list[str] | None = None) -> int:
    """``python train.py …``: the exit status. Through :func:`dacr_learn.console.run_cli`, a mistake in the
    user's files or arguments is one line ``error: …``; Lightning's start-up chatter is dropped."""
    quiet_lightning_chatter()
    return run_cli(train_command, argv)


if __name__ == "__main__":
    sys.exit(run_command_line())
