"""Evaluate a saved hardware model (``python -m dacr_learn.hardware --save``) on a validation recording.

Prints one JSON line: offset-removed RMSE [mm], ±2σ coverage and Spearman(‖σ‖, ‖r‖) of its σ model,
and the same for its ensemble-only σ calibration (docs/hardware.md, "Uncertainty"). Evaluation only:
FTDCR v4's val.csv; never point it at a hidden hold-out.

Usage: python experiments/hardware_cv/saved_model_val.py CKPT VAL_CSV
e.g.   python experiments/hardware_cv/saved_model_val.py runs/ftdcr_v4_model/model.pt data/ftdcr_v4/val.csv
"""
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
torch.set_num_threads(1)

from dacr_learn.hardware.deploy.checkpoint import load_hardware_model  # noqa: E402
from dacr_learn.hardware.deploy.uncertainty import coverage, spearman  # noqa: E402
from dacr_learn.hardware.metrics import offset_removed_rmse  # noqa: E402
from dacr_learn.hardware.recording import load_recording  # noqa: E402


def scores(residual: torch.Tensor, sigma: torch.Tensor) -> dict:
    return {"coverage_2sigma": round(coverage(residual, sigma), 4),
            "spearman": round(spearman(sigma.norm(dim=-1), residual.norm(dim=-1)), 3)}


def main(ckpt: str, val: str) -> dict:
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


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2])))
