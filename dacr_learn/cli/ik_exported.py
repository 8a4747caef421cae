"""``python -m dacr_learn.ik.exported``: export the warm-started IK refinement of a robot file
(:func:`dacr_learn.ik.exported.export_refinement`) and print each file's deviation from the eager refinement."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..ik import exported


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.ik.exported",
                                description=exported.__doc__.split("\n\n")[0])
    p.add_argument("--robot", required=True, help="robot YAML file")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--iterations", type=int, default=3, help="LM iterations per call (default 3)")
    p.add_argument("--position-only", action="store_true", help="targets are tip positions (B, 3)")
    p.add_argument("--no-aoti", action="store_true", help="skip the AOTInductor package (about a minute)")
    args = p.parse_args(argv)
    meta = exported.export_refinement(args.robot, args.out, iterations=args.iterations,
                                      position_only=args.position_only, aoti=not args.no_aoti)
    for name, dev in meta["max_abs_deviation"].items():
        print(f"{Path(args.out) / name}: max deviation from the eager refinement {dev:.2e}")
    return meta
