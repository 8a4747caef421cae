"""Export a trained model's inference modules, and load them back: the one entry for every checkpoint format.

    python -m dacr_learn.export --ckpt runs/default --out exports/default [--no-aoti]    # docs/export.md

(the command line: :mod:`dacr_learn.cli.export`)

:func:`export_checkpoint` reads the file once (:func:`~dacr_learn.hardware.deploy.checkpoint.read_model_file`)
and dispatches on what it holds:

- a saved hardware model (``python -m dacr_learn.hardware --save``):
  :func:`dacr_learn.hardware.deploy.export.export_hardware` (``fk``, ``jacobian`` [, ``initial_state``]);
- anything else is read as a ``train.py`` checkpoint (FK / IK): :func:`dacr_learn.deploy.export.export_trained`
  (``fk`` and ``jacobian``, or ``ik``), which names the file and what is wrong with it when it is not one.

Both write, verify and describe their files the same way (:mod:`dacr_learn.deploy.export`); :func:`load`
(``dacr_learn.load_exported``) loads any export. Neither needs Lightning (a checkpoint that lacks part of its
architecture's hyper-parameters is read through its LightningModule).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..deploy.export import (
    AUTOTUNE_CONFIGS,
    FORMAT,
    MAX_BATCH,
    METADATA_FILE,
    VERIFY_TOLERANCE,
    ExportedModule,
    export_program,
    export_trained,
    file_sha256,
    load,
    module_runner,
    read_metadata,
    write_module,
)
from ..hardware.deploy.checkpoint import hardware_model_from_blob, read_model_file
from ..hardware.deploy.export import export_hardware

__all__ = ["AUTOTUNE_CONFIGS", "FORMAT", "MAX_BATCH", "METADATA_FILE", "VERIFY_TOLERANCE", "ExportedModule",
           "export_checkpoint", "export_program", "file_sha256", "load", "module_runner", "read_metadata",
           "write_module"]


def export_checkpoint(ckpt: str | Path, out: str | Path, *, dtype: torch.dtype = torch.float32,
                      aoti: bool | tuple[str, ...] = True, autotune: bool = False) -> dict[str, Any]:
    """Export the inference modules of a checkpoint of any format (module docstring) to the folder ``out``;
    returns the metadata (also written to ``out/metadata.json``).

    ``aoti``: build AOTInductor packages for every module (True), none (False) or the named ones.
    ``autotune``: build them with :data:`AUTOTUNE_CONFIGS` (faster packages, slower export). Every written file
    is loaded back and compared with the checkpoint's model; above :data:`VERIFY_TOLERANCE` the export fails.
    """
    file = read_model_file(ckpt)                              # loaded once: recognised here, reused below
    if file.hardware:
        return export_hardware(file.path, out, dtype=dtype, aoti=aoti, autotune=autotune,
                               model=hardware_model_from_blob(file.blob, file.path))
    return export_trained(file.path, out, file.blob, dtype=dtype, aoti=aoti, autotune=autotune)

