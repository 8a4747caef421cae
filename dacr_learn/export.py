"""Export a trained model's inference modules, and load them back: the one entry for every checkpoint format.

    python -m dacr_learn.export --ckpt runs/default --out exports/default             # AOTInductor: ~1 min a module
    python -m dacr_learn.export --ckpt runs/default --out exports/default --no-aoti   # torch.export programs: seconds
    python -m dacr_learn.export --ckpt runs/ftdcr_v4_model/model.pt --out exports/ftdcr_v4 --no-aoti

:func:`export_checkpoint` reads the file once and dispatches on what it holds:

- a saved hardware model (``python -m dacr_learn.hardware --save``):
  :func:`dacr_learn.hardware.deploy.export.export_hardware` (``fk``, ``jacobian`` [, ``initial_state``]);
- anything else is read as a ``train.py`` checkpoint (FK / IK): :func:`dacr_learn.deploy.export.export_trained`
  (``fk`` and ``jacobian``, or ``ik``), which names the file and what is wrong with it when it is not one.

Both write, verify and describe their files the same way (:mod:`dacr_learn.deploy.export`); :func:`load`
(``dacr_learn.load_exported``) loads any export. Neither needs Lightning (a checkpoint that lacks part of its
architecture's hyper-parameters is read through its LightningModule).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import torch

from .checks import load_torch_file
from .console import run_cli
from .deploy.export import (
    AUTOTUNE_CONFIGS,
    DTYPES,
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
    output_folder,
    read_metadata,
    write_module,
)
from .hardware.deploy.checkpoint import hardware_model_from_blob, is_hardware_blob
from .hardware.deploy.export import export_hardware
from .runs import CHECKPOINT, find_checkpoint

__all__ = ["AUTOTUNE_CONFIGS", "FORMAT", "MAX_BATCH", "METADATA_FILE", "VERIFY_TOLERANCE", "ExportedModule",
           "export_checkpoint", "export_program", "file_sha256", "load", "main", "module_runner", "read_metadata",
           "write_module"]


def export_checkpoint(ckpt: str | Path, out: str | Path, *, dtype: torch.dtype = torch.float32,
                      aoti: bool | tuple[str, ...] = True, autotune: bool = False) -> dict[str, Any]:
    """Export the inference modules of a checkpoint of any format (module docstring) to the folder ``out``;
    returns the metadata (also written to ``out/metadata.json``).

    ``aoti``: build AOTInductor packages for every module (True), none (False) or the named ones.
    ``autotune``: build them with :data:`AUTOTUNE_CONFIGS` (faster packages, slower export). Every written file
    is loaded back and compared with the checkpoint's model; above :data:`VERIFY_TOLERANCE` the export fails.
    """
    ckpt = Path(ckpt)
    blob = load_torch_file(ckpt, CHECKPOINT)                  # loaded once: sniffed here, reused below
    if is_hardware_blob(blob):
        return export_hardware(ckpt, out, dtype=dtype, aoti=aoti, model=hardware_model_from_blob(blob, ckpt),
                               autotune=autotune)
    return export_trained(ckpt, out, blob, dtype=dtype, aoti=aoti, autotune=autotune)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """CLI: export a checkpoint; prints the written files and the verified deviations."""
    p = argparse.ArgumentParser(prog="python -m dacr_learn.export", description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", required=True,
                   help="FKModule / IKModule checkpoint, or a train.py run folder (runs/<name>: its newest "
                        "version's last.ckpt; runs/<name>/version_<n>), or a hardware model.pt")
    p.add_argument("--out", required=True, help="output folder (created with its parents if missing)")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="float32")
    p.add_argument("--no-aoti", action="store_true",
                   help="skip the AOTInductor packages (they compile for about a minute each; the torch.export "
                        "programs are written in seconds)")
    p.add_argument("--autotune", action="store_true",
                   help="build the AOTInductor packages with generated C++ GEMM kernels chosen by timing "
                        "(faster at batch 1, slower export)")
    args = p.parse_args(argv)
    if args.autotune and args.no_aoti:
        p.error("--autotune tunes the AOTInductor packages; it cannot be combined with --no-aoti")
    args.ckpt = str(find_checkpoint(args.ckpt))
    output_folder(args.out)                                   # fails fast, naming --out, when a file is in the way
    if not args.no_aoti:
        print(f"exporting {args.ckpt}: each AOTInductor package compiles for about a minute (--no-aoti skips them)",
              flush=True)
    meta = export_checkpoint(args.ckpt, args.out, dtype=DTYPES[args.dtype], aoti=not args.no_aoti,
                             autotune=args.autotune)
    print(f"exported {meta['task'].upper()} of robot {meta['robot']['name']!r} ({meta['features']} features, "
          f"{meta['dtype']}) from {args.ckpt} to {args.out}/")
    for f, dev in meta["max_abs_deviation"].items():
        print(f"  {f:<22} max |exported − checkpoint's model| = {dev:.2e}")
    print(f"  load with: dacr_learn.load_exported('{args.out}', '{next(iter(meta['modules']))}')")
    return meta


if __name__ == "__main__":
    sys.exit(run_cli(main))       # a bad --ckpt or --out: its one-line message, not a traceback
