"""Direction-dependent capstan friction inside the slack-aware tendon model (research script).

Each tendon i loses tension along its path by Coulomb friction at the spacer discs: at segment k
the tension is T_i·(1 − σ_i·μ·W_ik), with W_ik the wrap angle from the base to the middle of
segment k (bends of the proximal segments + half of segment k's own bend, from the frictionless
solution) and σ_i ∈ [−1, 1] the direction the tendon was last moved in (+1 pulled in: friction
opposes the pull and the distal segments see less tension; −1 paid out: more), from a play
operator of width ``--sigma-width`` on its command. The moment balance uses the reduced
tensions, the tendon stretch the plain path (``solve_tendon_qp`` with a force map).
One extra parameter, μ, fitted with the CC parameters on the training rows. ~1 min.
(--extrap: fit on the single-segment family, test on all pairs; --val reads FTDCR v4's val.csv)

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `capstan_hysteresis.py`: μ = 0.20, val 7.35 mm) and "2026-11-21:
Third round: static physics and a better selection proxy" (`--extrap`).
Run from the repository root:
    python -m research.hardware_cv.capstan_hysteresis [--sigma-width 1e-4 ...] [--val | --extrap]
"""

import argparse
import json
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.slack import solve_tendon_qp

from .common import FOLDS, rmse, setup, tendon_play, val_data

SCALES = {"mu": 0.05}  # extra fit_cc scale of the friction coefficient


class CapstanCC(CalibratedCC):
    def __init__(self, spec, mu0=0.0):
        super().__init__(spec)
        self.mu = nn.Parameter(torch.tensor(float(mu0), dtype=torch.float64))
        self.sigma = None  # (n, N) set before calling

    def clarke_with_friction(self, x):
        enc, m = self.encoder, self.spec.num_segments
        d = enc.effective_radius()
        bend_w, tendon_w = enc.bend_weights(), 1.0 / enc.path_length
        g = enc.displacement_map()  # (N, 2m)
        xp = x + enc.pretension
        with torch.no_grad():  # wrap angles from the frictionless shape
            rho0 = solve_tendon_qp(xp, g, bend_w, tendon_w).unflatten(-1, (m, 2))
            th = rho0.norm(dim=-1) / d  # (n, m)
            wrap = torch.cat([torch.zeros_like(th[:, :1]), th.cumsum(-1)[:, :-1]], -1) + th / 2
        factor = 1 - self.mu * self.sigma.unsqueeze(-1) * wrap.unsqueeze(-2)  # (n, N, m)
        gf = g * factor.repeat_interleave(2, dim=-1)  # (n, N, 2m) force map
        rho = solve_tendon_qp(xp, g, bend_w, tendon_w, force_map=gf)
        return rho.unflatten(-1, (m, 2))

    def forward(self, x):
        return self.tip_from_features(self.encoder.features_from_clarke(self.clarke_with_friction(x)))


def direction(x, width):
    return (x - tendon_play(x, width)) / width


def fit_capstan(x, tip, sigma, mu0=0.05):
    spec = setup().spec
    base = CalibratedCC(spec)
    fit_cc(base, x, tip, scales=SCALES)  # start from the frictionless fit
    cc = CapstanCC(spec, mu0)
    cc.load_state_dict({**base.state_dict(), "mu": cc.mu.detach()})
    cc.sigma = sigma
    info = fit_cc(cc, x, tip, scales=SCALES)
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc, info


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sigma-width", type=float, nargs="+", default=[2e-5, 5e-5, 1e-4, 2e-4, 4e-4])
    ap.add_argument("--val", action="store_true")
    ap.add_argument("--extrap", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    for w in args.sigma_width:
        t0 = time.time()
        sig = direction(x_tr, w)
        cc, info = fit_capstan(x_tr, tip_tr, sig)
        cc.sigma = sig
        with torch.no_grad():
            train = rmse(cc(x_tr), tip_tr)
        out = {"sigma_width_mm": w * 1e3, "mu": round(float(cc.mu), 4), "train": round(train, 3)}
        if args.val:
            x_va, tip_va = val_data()
            x_all = torch.cat([x_tr, x_va])
            sig_all = direction(x_all, w)  # causal: history runs on
            cc.sigma = sig_all[len(x_tr) :]
            with torch.no_grad():
                out["VAL"] = round(rmse(cc(x_va), tip_va), 3)
        elif args.extrap:
            single = torch.from_numpy(fam == "single")
            c, _ = fit_capstan(x_tr[single], tip_tr[single], sig[single])
            c.sigma = sig[~single]
            with torch.no_grad():
                out.update(
                    singles_to_pairs=round(rmse(c(x_tr[~single]), tip_tr[~single]), 3), mu_singles=round(float(c.mu), 4)
                )
        else:
            folds = {}
            for f in FOLDS:
                tr = torch.from_numpy(fam != f)
                c, _ = fit_capstan(x_tr[tr], tip_tr[tr], sig[tr])
                c.sigma = sig[~tr]
                with torch.no_grad():
                    folds[f] = (rmse(c(x_tr[~tr]), tip_tr[~tr]), round(float(c.mu), 3))
            out.update(cv=round(float(np.mean([v[0] for v in folds.values()])), 3), folds=folds)
        out["s"] = round(time.time() - t0, 1)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
