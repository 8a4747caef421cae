"""Compositional hardware model (issue 13, item 7): hyperparameters scored with the library's train-only proxies.

    python experiments/hardware_cv/compositional_sweep.py ROBOT PROXIES VARIANT [VARIANT ...]

ROBOT: v4 | v6 (configs/robots/ftdcr_<robot>_calibrated.yaml, data/ftdcr_<robot>/train.csv; no val is read).
PROXIES: extrap,cv (each proxy is scored for every variant before the next proxy starts).
VARIANT: comma-separated key=value arguments of ``CCCompositionalResidual`` (context, width, depth,
weight_decay, torsion, steps, lr), e.g. ``context=distal,weight_decay=1e-3``; ``default`` for the defaults.
One JSON line per (variant, proxy) on stdout, seed 0.
"""
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
torch.set_num_threads(1)

from dacr_learn.hardware.compositional_model import CCCompositionalResidual  # noqa: E402
from dacr_learn.hardware.recording import load_recording  # noqa: E402
from dacr_learn.hardware.servo_map import ServoMap  # noqa: E402
from dacr_learn.hardware.study.registry import ModelInfo  # noqa: E402
from dacr_learn.hardware.study.selection import make_folds, proxy_masks, proxy_scores  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402

CASTS = {"context": str, "width": int, "depth": int, "weight_decay": float, "steps": int, "lr": float,
         "torsion": lambda v: v.lower() in ("1", "true")}


def parse(variant: str) -> dict:
    if variant == "default":
        return {}
    pairs = [item.split("=", 1) for item in variant.split(",")]
    return {k: CASTS[k](v) for k, v in pairs}


def info(variant: str) -> ModelInfo:
    kwargs = parse(variant)
    return ModelInfo(variant, "?", lambda c, s: CCCompositionalResidual(c.train, c.cc, **kwargs), "clarke")


def main(robot: str, proxies: str, variants: list[str]) -> None:
    path = ROOT / "configs" / "robots" / f"ftdcr_{robot}_calibrated.yaml"
    spec = RobotSpec.from_yaml(path)
    smap = ServoMap.from_yaml(path.parent / "servo_maps" / path.name)
    rec = load_recording(ROOT / "data" / f"ftdcr_{robot}" / "train.csv", spec)
    masks = proxy_masks(rec.labels)
    for proxy in proxies.split(","):
        folds = {proxy: make_folds(rec, spec, smap, masks[proxy])}
        for v in variants:
            start = time.perf_counter()
            scores = proxy_scores(info(v), folds, [0])
            print(json.dumps({"robot": robot, "variant": v, "proxy": proxy, "mm": scores[proxy],
                              "folds": scores[proxy + "_folds"], "seconds": round(time.perf_counter() - start, 1)}),
                  flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
