"""Compositional hardware model (issue 13, item 7): hyperparameters scored with the library's train-only proxies.

ROBOT: v4 | v6 (configs/robots/ftdcr_<robot>_calibrated.yaml, data/ftdcr_<robot>/train.csv; no val is read).
PROXIES: extrap,cv (each proxy is scored for every variant before the next proxy starts).
VARIANT: comma-separated key=value arguments of ``CCCompositionalResidual`` (context, width, depth,
weight_decay, torsion, steps, lr), e.g. ``context=distal,weight_decay=1e-3``; ``default`` for the defaults.
One JSON line per (variant, proxy) on stdout, seed 0 (the docs' lines are in results/compositional_sweep.jsonl);
~100–230 s per fit on a loaded machine.

Numbers: docs/history/compositional.md, "On the real robots: hardware model `cc_compositional_residual`"
(the design chosen on the singles → pairs proxy).
Run from the repository root: python -m research.hardware_cv.compositional_sweep ROBOT PROXIES VARIANT [VARIANT ...]
e.g.   python -m research.hardware_cv.compositional_sweep v4 extrap default context=distal,weight_decay=1e-3
"""
import json
import sys
import time

import torch

from dacr_learn.hardware.compositional_model import CCCompositionalResidual
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.registry import ModelInfo
from dacr_learn.hardware.study.selection import make_folds, proxy_masks
from dacr_learn.robot import RobotSpec

from .common import ROOT, variant_scores

CASTS = {"context": str, "width": int, "depth": int, "weight_decay": float, "steps": int, "lr": float,
         "torsion": lambda v: v.lower() in ("1", "true")}


def parse(variant: str) -> dict:
    if variant == "default":
        return {}
    pairs = [item.split("=", 1) for item in variant.split(",")]
    return {k: CASTS[k](v) for k, v in pairs}


def info(variant: str) -> ModelInfo:
    kwargs = parse(variant)
    return ModelInfo(variant, lambda c, s: CCCompositionalResidual(c.cc, **kwargs), "clarke")


def run(robot: str, proxies: str, variants: list[str]) -> None:
    path = ROOT / "configs" / "robots" / f"ftdcr_{robot}_calibrated.yaml"
    spec = RobotSpec.from_yaml(path)
    smap = ServoMap.from_yaml(path.parent / "servo_maps" / path.name)
    rec = load_recording(ROOT / "data" / f"ftdcr_{robot}" / "train.csv", spec)
    masks = proxy_masks(rec.labels)
    for proxy in proxies.split(","):
        folds = {proxy: make_folds(rec, spec, smap, masks[proxy])}
        for v in variants:
            start = time.perf_counter()
            scores = variant_scores(info(v), folds, [0])
            print(json.dumps({"robot": robot, "variant": v, "proxy": proxy, "mm": scores[proxy],
                              "folds": scores[proxy + "_folds"], "seconds": round(time.perf_counter() - start, 1)}),
                  flush=True)


def main() -> None:
    torch.set_num_threads(1)
    run(sys.argv[1], sys.argv[2], sys.argv[3:])


if __name__ == "__main__":
    main()
