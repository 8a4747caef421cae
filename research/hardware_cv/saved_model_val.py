"""Evaluate a saved hardware model (``python -m dacr_learn.hardware --save``) on a validation recording.

Prints one JSON line: offset-removed RMSE [mm], ±2σ coverage and Spearman(‖σ‖, ‖r‖) of its σ model,
and the same for its ensemble-only σ calibration. Evaluation only: FTDCR v4's val.csv; never point it
at a hidden hold-out. Seconds.

Numbers: docs/history/hardware.md, "2026-11-23: Uncertainty: σ per prediction and out-of-support
score" (the re-measurement on the `--save runs/ftdcr_v4_model` model), docs/results.md and README.md
(uncertainty on v4 val: 92.3 %, 0.56).
Run from the repository root: python -m research.hardware_cv.saved_model_val CKPT VAL_CSV
e.g.   python -m research.hardware_cv.saved_model_val runs/ftdcr_v4_model/model.pt data/ftdcr_v4/val.csv
"""
import json
import sys

import torch

from dacr_learn.hardware.deploy.checkpoint import load_hardware_model
from dacr_learn.hardware.deploy.uncertainty import coverage, spearman
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording


def scores(residual: torch.Tensor, sigma: torch.Tensor) -> dict:
    return {"coverage_2sigma": round(coverage(residual, sigma), 4),
            "spearman": round(spearman(sigma.norm(dim=-1), residual.norm(dim=-1)), 3)}


def evaluate(ckpt: str, val: str) -> dict:
    model = load_hardware_model(ckpt)
    rec = load_recording(val, model.spec)
    split = model.split(1e3 * rec.servo)
    tip, sigma = model.predict(split)
    residual = tip - rec.tip
    residual = residual - residual.mean(0)                 # offset removed, as the lab's metric
    out = {"model": model.name, "members": len(model.members), "sigma_model": model.sigma_model.describe(),
           "val_rmse_mm": round(float(offset_removed_rmse(tip, rec.tip)) * 1e3, 3), **scores(residual, sigma),
           "median_sigma_mm": round(float(sigma.norm(dim=-1).median()) * 1e3, 2)}
    model.sigma_model = None                               # the ensemble-only σ calibration
    out["ensemble_only"] = scores(residual, model.predict(split)[1])
    return out


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        sys.exit("usage: python -m research.hardware_cv.saved_model_val CKPT VAL_CSV")
    torch.set_num_threads(1)
    print(json.dumps(evaluate(args[0], args[1])))


if __name__ == "__main__":
    main()
