"""``python -m dacr_learn.export``: export a checkpoint of any format (:func:`dacr_learn.export.export_checkpoint`);
prints the written files and the verified deviations."""
from __future__ import annotations

import argparse
from typing import Any

from .. import export
from ..deploy.export import DTYPES, output_folder
from ..runs import find_checkpoint


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """CLI: export a checkpoint; prints the written files and the verified deviations."""
    p = argparse.ArgumentParser(prog="python -m dacr_learn.export", description=export.__doc__.split("\n\n")[0])
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
    meta = export.export_checkpoint(args.ckpt, args.out, dtype=DTYPES[args.dtype], aoti=not args.no_aoti,
                                    autotune=args.autotune)
    print(f"exported {meta['task'].upper()} of robot {meta['robot']['name']!r} ({meta['features']} features, "
          f"{meta['dtype']}) from {args.ckpt} to {args.out}/")
    for f, dev in meta["max_abs_deviation"].items():
        print(f"  {f:<22} max |exported − checkpoint's model| = {dev:.2e}")
    print(f"  load with: dacr_learn.load_exported('{args.out}', '{next(iter(meta['modules']))}')")
    return meta
