"""How well train identifies the motion-capture marker's offset along the tip axis: the CC model
refitted with the offset fixed at several values (the base translation absorbs the rest); family CV
and the singles → pairs extrapolation score.
Usage: python experiments/hardware_cv/marker_offset.py"""

import json

import numpy as np
import torch
from common import FOLDS, CalibratedCC, fam, fit_cc, rmse, spec, tip_tr, x_tr


def fit_fixed(x, tip, offset):
    cc = CalibratedCC(spec)
    with torch.no_grad():
        cc.tip_offset.fill_(offset)
    fit_cc(cc, x, tip, frozen=("tip_offset",))
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc


for offset in (0.0, 2e-3, 4e-3, 6e-3, 8.43e-3, 12e-3):
    cc = fit_fixed(x_tr, tip_tr, offset)
    folds = {}
    for f in FOLDS:
        tr = torch.from_numpy(fam != f)
        folds[f] = rmse(fit_fixed(x_tr[tr], tip_tr[tr], offset)(x_tr[~tr]), tip_tr[~tr])
    single = torch.from_numpy(fam == "single")
    extrap = rmse(fit_fixed(x_tr[single], tip_tr[single], offset)(x_tr[~single]), tip_tr[~single])
    print(
        json.dumps(
            {
                "marker_offset_mm": offset * 1e3,
                "train": round(rmse(cc(x_tr), tip_tr), 3),
                "singles_to_pairs": round(extrap, 3),
                "cv": round(float(np.mean(list(folds.values()))), 3),
                "folds": {k: round(v, 2) for k, v in folds.items()},
                "base_z_mm": round(float(cc.base_translation[2]) * 1e3, 2),
            }
        ),
        flush=True,
    )
