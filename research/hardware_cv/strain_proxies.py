"""Train-only proxies of the CC-based models with the base vs the pretension-strain CC model (issue 12).

For each CC variant (``selection.CC_VARIANTS``: base, strain) the folds are built with that CC model
(refitted per fold) and every model named gets its family CV and singles → pairs scores (seed 0).
One JSON line per (variant, model) appended to results/strain_proxies.jsonl.

Usage: python experiments/hardware_cv/strain_proxies.py ROBOT MODELS      (ROBOT: v4 | v6; MODELS: a,b,…)
e.g.   python experiments/hardware_cv/strain_proxies.py v4 cc,cc_clarke_residual_history,cc_clarke_residual
About 1.5 min per learned model and variant on a quiet core.
"""
import json
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
torch.set_num_threads(1)

from dacr_learn.hardware.recording import load_recording  # noqa: E402
from dacr_learn.hardware.study.benchmark import resolve_robot  # noqa: E402
from dacr_learn.hardware.study.selection import CC_VARIANTS, make_folds, proxy_masks, proxy_scores  # noqa: E402

OUT = ROOT / "experiments/hardware_cv/results/strain_proxies.jsonl"


def main(robot: str, models: list[str]) -> None:
    spec, smap, _ = resolve_robot(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml", None, None,
                                  Path(tempfile.mkdtemp()), "mm")
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


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2].split(","))
