"""Gravity inside the slack-aware tendon model (research script).

The backbone's weight is an external load. Its generalised force on the Clarke coordinates,
f = −γ ∂Z/∂ρ with Z = Σ_s z_s the summed height (mocap z, after the fitted base tilt) of
backbone points spread evenly along the robot (plus ``--tip-mass`` times the tip point), is
evaluated at the gravity-free solution ρ₀ and added to the force balance (one step):

    bend_w ρ = Gᵀ W_a (x − Gρ) + f(ρ₀)     (``solve_tendon_qp(..., load=f)``)

γ [m, same units as the encoder's energy, divided by EA] is fitted with the CC parameters; γ > 0
lowers the points along mocap −z, γ < 0 along +z (the sign is not assumed: it is fitted).
Static CC only. Reports train RMSE, leave-one-family-out CV RMSE and the singles → pairs
extrapolation RMSE (--val: also FTDCR v4's val.csv). ~25 s per mass.

Numbers: docs/history/hardware.md, "2026-11-21: Third round: static physics and a better selection
proxy" (row `gravity.py`, tip mass 0 / 1).
Run from the repository root: python -m research.hardware_cv.gravity [--tip-mass 0 1] [--val]
"""

import argparse
import json
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.slack import solve_tendon_qp
from dacr_learn.kinematics import backbone_points

from .common import FOLDS, rmse, setup, val_data

SCALES = {"gravity": 1e-5}  # extra fit_cc scale of the gravity load
POINTS = 8  # backbone points per segment


class GravityCC(CalibratedCC):
    def __init__(self, spec, tip_mass: float):
        super().__init__(spec)
        self.tip_mass = tip_mass
        self.gravity = nn.Parameter(torch.zeros((), dtype=torch.float64))

    def height(self, rho):
        """(B,) summed mocap-z of the backbone points (+ tip_mass × tip) for ρ (B, 2m)."""
        m = self.spec.num_segments
        pts = self.to_world(
            backbone_points(self.spec, self.encoder.features_from_clarke(rho.unflatten(-1, (m, 2))), POINTS)
        )[..., 1:, :]
        return pts[..., 2].sum(-1) / pts.shape[-2] + self.tip_mass * pts[..., -1, 2]

    def encode(self, x):
        enc, m = self.encoder, self.spec.num_segments
        bend_w, tendon_w, g, xp = enc.bend_weights(), 1.0 / enc.path_length, enc.displacement_map(), x + enc.pretension
        rho0 = solve_tendon_qp(xp, g, bend_w, tendon_w)
        with torch.enable_grad():
            r = rho0.detach().requires_grad_(True)
            dz = torch.autograd.grad(self.height(r).sum(), r)[0]  # ∂Z/∂ρ at ρ₀ (B, 2m)
        rho = solve_tendon_qp(xp, g, bend_w, tendon_w, load=-self.gravity * dz)
        return self.encoder.features_from_clarke(rho.unflatten(-1, (m, 2)))

    def forward(self, x):
        return self.tip_from_features(self.encode(x))


def fitted(tip_mass, x, tip):
    cc = GravityCC(setup().spec, tip_mass)
    fit_cc(cc, x, tip, scales=SCALES)
    return cc


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tip-mass", type=float, nargs="+", default=[0.0])
    ap.add_argument("--val", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    for tm in a.tip_mass:
        t0 = time.time()
        cc = fitted(tm, x_tr, tip_tr)
        with torch.no_grad():
            out = {"name": f"gravity_tipmass{tm}", "train": round(rmse(cc(x_tr), tip_tr), 3)}
        folds = {}
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            with torch.no_grad():
                folds[f] = rmse(fitted(tm, x_tr[tr], tip_tr[tr])(x_tr[~tr]), tip_tr[~tr])
        single = torch.from_numpy(fam == "single")
        with torch.no_grad():
            out["singles_to_pairs"] = round(
                rmse(fitted(tm, x_tr[single], tip_tr[single])(x_tr[~single]), tip_tr[~single]), 3
            )
        out.update(
            cv=round(float(np.mean(list(folds.values()))), 3),
            folds={k: round(s, 2) for k, s in folds.items()},
            gravity=cc.gravity.item(),
            report=cc.report(),
        )
        if a.val:
            x_va, tip_va = val_data()
            with torch.no_grad():
                out["VAL"] = round(rmse(cc(x_va), tip_va), 3)
        out["s"] = round(time.time() - t0, 1)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
