"""Static CC model fitted without the single-tendon pull rows (``tendon<k>`` labels), scored with the
library's train-only proxies on the same test rows as the package model (pull rows stay in the tests).
JSON lines for the fits with / without pulls; 12 CC fits.

Numbers: docs/history/hardware.md, "2026-11-23: Carrying Clarke-space models over between robots"
(row "static CC fitted without the tendon-pull rows").
Run from the repository root: python -m research.hardware_cv.cc_no_pulls ROBOT   (ROBOT: v4 | v6)
"""
import json
import re
import sys

import numpy as np
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.selection import proxy_masks
from dacr_learn.robot import RobotSpec

from .common import ROOT


def main() -> None:
    torch.set_num_threads(1)
    robot = sys.argv[1]
    spec = RobotSpec.from_yaml(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml")
    smap = ServoMap.from_yaml(ROOT / f"configs/robots/servo_maps/ftdcr_{robot}_calibrated.yaml")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)
    x, tip = smap.displacements(spec, rec), rec.tip
    pull = np.array([bool(re.search(r"tendon\d+", label)) for label in rec.labels])
    masks = proxy_masks(rec.labels)
    for drop in (False, True):
        out = {"robot": robot, "fit_without_pulls": drop}
        for proxy, folds in masks.items():
            per = {}
            for name, tr, te in folds:
                tr = torch.from_numpy(tr & ~pull if drop else tr)
                te = torch.from_numpy(te)
                cc = CalibratedCC(spec)
                fit_cc(cc, x[tr], tip[tr])
                with torch.no_grad():
                    per[name] = round(float(offset_removed_rmse(cc(x[te]), tip[te])) * 1e3, 3)
            out[proxy], out[proxy + "_folds"] = round(float(np.mean(list(per.values()))), 3), per
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
