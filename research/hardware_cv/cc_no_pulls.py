"""Static CC model fitted without the single-tendon pull rows (``tendon<k>`` labels), scored with the
library's train-only proxies on the same test rows as the package model (pull rows stay in the tests).

Usage: python experiments/hardware_cv/cc_no_pulls.py ROBOT   → JSON lines for fits with / without pulls.
"""
import json
import re
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
torch.set_num_threads(1)

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc  # noqa: E402
from dacr_learn.hardware.metrics import offset_removed_rmse  # noqa: E402
from dacr_learn.hardware.recording import load_recording  # noqa: E402
from dacr_learn.hardware.servo_map import ServoMap  # noqa: E402
from dacr_learn.hardware.study.selection import proxy_masks  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402


def main() -> None:
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
