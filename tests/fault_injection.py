"""Callbacks that stop a training run the way a user or a scheduler does, for the run-handling tests.

Named in a run's YAML config (``trainer.callbacks``: ``class_path: fault_injection.SigtermAt``), so
they also work in a ``train.py`` subprocess started with ``tests/`` on ``PYTHONPATH``.
"""
import os
import signal

import lightning.pytorch as pl


class SigtermAt(pl.Callback):
    """Sends SIGTERM to its own process after training batch ``step`` (global step), once."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


class InterruptAt(pl.Callback):
    """Raises KeyboardInterrupt (what Ctrl-C does) after training batch ``step``."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step == self.step:
            raise KeyboardInterrupt
