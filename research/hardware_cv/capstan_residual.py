"""Model (g) on top of the capstan-friction CC model instead of the frictionless one (research script).

The capstan model (``capstan_hysteresis.py``, σ from a 0.02 mm play on each tendon command, μ
fitted) couples the segments' hysteresis through the wrap angle of the proximal segments; the (g)
residual network (``residual_memory.py``) then corrects each segment as before.
(EXTRAP: fit on the single-segment family, test on all pairs, as in residual_memory.py; VAL reads
FTDCR v4's val.csv) ~40 s per seed (CV).

Numbers: docs/history/hardware.md, "2026-11-21: Third round: static physics and a better selection
proxy" (row "(g) on the capstan CC model").
Run from the repository root: python -m research.hardware_cv.capstan_residual SEEDS [CV|EXTRAP|VAL]
e.g.   python -m research.hardware_cv.capstan_residual 0,1,2 CV
"""

import json
import sys
import time

import numpy as np
import torch
from torch import nn

from .capstan_hysteresis import direction, fit_capstan
from .common import FOLDS, setup, val_data
from .residual_memory import run

SIGMA_WIDTH = 2e-5
CFG = {"width": 1e-4, "mem_in": True, "lin": [], "c0": False}


class CapstanView(nn.Module):
    """The interface residual_memory expects (encoder(x) → features, tip_from_features) for a
    fitted capstan model and the tendon directions σ of the rows it will see."""

    def __init__(self, cap, sigma):
        super().__init__()
        self.cap, self.sigma = cap, sigma

    def encoder(self, x):
        self.cap.sigma = self.sigma
        return self.cap.encoder.features_from_clarke(self.cap.clarke_with_friction(x))

    def tip_from_features(self, f):
        return self.cap.tip_from_features(f)


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    seeds = [int(s) for s in sys.argv[1].split(",")]
    mode = sys.argv[2] if len(sys.argv) > 2 else "CV"
    t0 = time.time()
    if mode == "VAL":
        x_va, tip_va = val_data()
        x_all, tip_all = torch.cat([x_tr, x_va]), torch.cat([tip_tr, tip_va])
        sig = direction(x_all, SIGMA_WIDTH)
        tr = torch.arange(len(x_all)) < len(x_tr)
        cap, _ = fit_capstan(x_tr, tip_tr, sig[tr])
        res = [run(CFG, CapstanView(cap, sig), x_all, tip_all, tr, ~tr, s)[0] for s in seeds]
        print(
            json.dumps(
                {
                    "name": "capstan_g01",
                    "VAL": [round(r, 3) for r in res],
                    "val_mean": round(float(np.mean(res)), 3),
                    "mu": round(float(cap.mu), 4),
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )
    elif mode == "EXTRAP":
        sig = direction(x_tr, SIGMA_WIDTH)
        tr = torch.from_numpy(fam == "single")
        cap, _ = fit_capstan(x_tr[tr], tip_tr[tr], sig[tr])
        res = [run(CFG, CapstanView(cap, sig), x_tr, tip_tr, tr, ~tr, s)[0] for s in seeds]
        print(
            json.dumps(
                {
                    "name": "capstan_g01",
                    "singles_to_pairs": round(float(np.mean(res)), 3),
                    "per_seed": [round(r, 3) for r in res],
                    "mu": round(float(cap.mu), 4),
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )
    else:
        sig = direction(x_tr, SIGMA_WIDTH)
        per = {}
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            cap, _ = fit_capstan(x_tr[tr], tip_tr[tr], sig[tr])
            per[f] = float(np.mean([run(CFG, CapstanView(cap, sig), x_tr, tip_tr, tr, ~tr, s)[0] for s in seeds]))
        print(
            json.dumps(
                {
                    "name": "capstan_g01",
                    "cv": round(float(np.mean(list(per.values()))), 3),
                    "folds": {k: round(v, 2) for k, v in per.items()},
                    "seeds": seeds,
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
