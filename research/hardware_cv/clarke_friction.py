"""Coulomb friction at the spacer discs as a play on each segment's Clarke coordinates whose width
follows the linearised capstan law, w_k = mu * wrap_k * |rho_k| + w0 (wrap_k = bend of the proximal
segments + half of segment k's own bend), in the CC model (refitted twice with the correction
from the previous fit). One JSON line per (mu, w0); ~2 min.

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `clarke_friction.py`).
Run from the repository root: python -m research.hardware_cv.clarke_friction ['[[mu, w0_m], ...]']
(default grid [[0, 0], [0.05, 0], [0.1, 0], [0.2, 0], [0, 5e-5], [0.1, 5e-5]])
"""
import json
import sys

import numpy as np
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.learned import play_operator

from .common import FOLDS, rmse, setup

DEFAULT_GRID = [[0, 0], [0.05, 0], [0.1, 0], [0.2, 0], [0, 5e-5], [0.1, 5e-5]]


def friction_delta(rho, mu, w0):
    th = rho.norm(dim=-1) / setup().radius
    wrap = torch.cat([torch.zeros_like(th[:, :1]), th.cumsum(-1)[:, :-1]], -1) + th / 2
    return play_operator(rho, (mu * wrap * rho.norm(dim=-1) + w0).clamp_min(1e-12)) - rho


class FrictionCC(CalibratedCC):
    delta = None

    def forward(self, x):
        f = self.encoder(x)
        if self.delta is not None:
            f = torch.cat([f[..., :2] + self.delta, f[..., 2:]], -1)
        return self.tip_from_features(f)


def fit_friction(tr, mu, w0, rounds=2):
    d = setup()
    x_tr, tip_tr = d.x_tr, d.tip_tr
    cc = FrictionCC(d.spec)
    fit_cc(cc, x_tr[tr], tip_tr[tr])
    for _ in range(rounds):
        with torch.no_grad():
            cc.delta = None
            delta = friction_delta(cc.encoder(x_tr)[..., :2], mu, w0)   # along the whole recording (causal)
        cc.delta = delta[tr]
        fit_cc(cc, x_tr[tr], tip_tr[tr])
    with torch.no_grad():
        cc.delta = None
        cc.delta = friction_delta(cc.encoder(x_tr)[..., :2], mu, w0)
        return cc(x_tr)


def main() -> None:
    torch.set_num_threads(1)
    grid = json.loads(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_GRID
    d = setup()
    for mu, w0 in grid:
        pred = fit_friction(torch.ones(len(d.x_tr), dtype=torch.bool), mu, w0)
        folds = {}
        for f in FOLDS:
            tr = torch.from_numpy(d.fam != f)
            folds[f] = rmse(fit_friction(tr, mu, w0)[~tr], d.tip_tr[~tr])
        print(json.dumps({"mu": mu, "w0_mm": w0 * 1e3, "train": round(rmse(pred, d.tip_tr), 3),
                          "cv": round(float(np.mean(list(folds.values()))), 3),
                          "folds": {k: round(v, 2) for k, v in folds.items()}}), flush=True)


if __name__ == "__main__":
    main()
