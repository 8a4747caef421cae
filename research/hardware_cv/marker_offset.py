"""How well train identifies the motion-capture marker's offset along the tip axis: the CC model
refitted with the offset fixed at several values (the base translation absorbs the rest); family CV
and the singles → pairs extrapolation score. One JSON line per offset.

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" ("The marker offset matters at large bends") and "2026-11-21: Third
round: static physics and a better selection proxy" (EXTRAP flat over 0–12 mm). ~40 s.
Run from the repository root: python -m research.hardware_cv.marker_offset
"""

import json

import numpy as np
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc

from .common import FOLDS, rmse, setup


def fit_fixed(x, tip, offset):
    cc = CalibratedCC(setup().spec)
    with torch.no_grad():
        cc.tip_offset.fill_(offset)
    fit_cc(cc, x, tip, frozen=("tip_offset",))
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
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


if __name__ == "__main__":
    main()
