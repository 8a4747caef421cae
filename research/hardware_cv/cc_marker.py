"""Static CC model with the tip-marker offset fixed (not fitted), scored with the library's train-only
proxies on one robot (FTDCR v6's free fit puts the marker 25 mm *behind* the tip: unphysical).
One JSON line per offset: train RMSE, family CV, singles→pairs extrapolation [mm], fitted parameters;
~6 CC fits per offset.

Numbers: docs/history/hardware.md, "2026-11-23: FTDCR v6, the second robot" (marker offset fixed at
0 / 15 mm).
Run from the repository root: python -m research.hardware_cv.cc_marker ROBOT OFFSETS_MM   (e.g. v6 free,0,15)
"""
import json
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


def fitted(spec, x, tip, offset):
    cc = CalibratedCC(spec)
    if offset == "free":
        fit_cc(cc, x, tip)
    else:
        with torch.no_grad():
            cc.tip_offset.fill_(float(offset) * 1e-3)
        fit_cc(cc, x, tip, frozen=("tip_offset",))
    return cc


def main() -> None:
    torch.set_num_threads(1)
    robot, offsets = sys.argv[1], sys.argv[2].split(",")
    spec = RobotSpec.from_yaml(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml")
    smap = ServoMap.from_yaml(ROOT / f"configs/robots/servo_maps/ftdcr_{robot}_calibrated.yaml")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)
    x, tip = smap.displacements(spec, rec), rec.tip
    masks = proxy_masks(rec.labels)
    for off in offsets:
        out = {"robot": robot, "tip_offset_mm": off}
        for proxy, folds in masks.items():
            per = {}
            for name, tr, te in folds:
                tr, te = torch.from_numpy(tr), torch.from_numpy(te)
                cc = fitted(spec, x[tr], tip[tr], off)
                with torch.no_grad():
                    per[name] = round(float(offset_removed_rmse(cc(x[te]), tip[te])) * 1e3, 3)
            out[proxy] = round(float(np.mean(list(per.values()))), 3)
            out[proxy + "_folds"] = per
        cc = fitted(spec, x, tip, off)
        with torch.no_grad():
            out["train"] = round(float(offset_removed_rmse(cc(x), tip)) * 1e3, 3)
        out["parameters"] = cc.report()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
