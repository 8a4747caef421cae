"""Train-only proxies of the CC-based models with the base vs the pretension-strain CC model (issue 12).

For each CC variant (``selection.CC_VARIANTS``: base, strain) the folds are built with that CC model
(refitted per fold) and every model named gets its family CV and singles → pairs scores (seed 0).
One JSON line per (variant, model) appended to results/strain_proxies.jsonl.
About 1.5 min per learned model and variant on a quiet core.

Numbers: docs/history/hardware.md, "2026-11-23: Fourth round: pretension that grows with the tendon
length, chosen per robot" (the proxies of the CC-based models with the strain variant).
Run from the repository root: python -m research.hardware_cv.strain_proxies ROBOT MODELS   (ROBOT: v4 | v6;
MODELS: a,b,…)
e.g.   python -m research.hardware_cv.strain_proxies v4 cc,cc_clarke_residual_history,cc_clarke_residual
"""
import json
import sys
import tempfile
from pathlib import Path

import torch

from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.study.benchmark import resolve_robot
from dacr_learn.hardware.study.selection import CC_VARIANTS, make_folds, proxy_masks, proxy_scores

from .common import RESULTS, ROOT

OUT = RESULTS / "strain_proxies.jsonl"


def run(robot: str, models: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:    # only written to when calibrating from pulls, never here
        spec, smap, _ = resolve_robot(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml", None, None,
                                      Path(tmp), "mm")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)      # train only, never val
    masks = proxy_masks(list(rec.labels))
    for variant, options in CC_VARIANTS.items():
        folds = {p: make_folds(rec, spec, smap, masks[p], options) for p in ("cv", "extrap")}
        for model in models:
            scores = proxy_scores(model, folds, [0])
            line = {"robot": robot, "cc_variant": variant, "model": model, "cv": scores["cv"],
                    "extrap": scores["extrap"], "cv_folds": scores["cv_folds"]}
            print(json.dumps(line), flush=True)
            with OUT.open("a") as f:
                f.write(json.dumps(line) + "\n")


def main() -> None:
    torch.set_num_threads(1)
    run(sys.argv[1], sys.argv[2].split(","))


if __name__ == "__main__":
    main()
