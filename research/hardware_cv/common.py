"""Shared set-up of the hardware cross-validation experiments (research scripts, not library code).

FTDCR v4 by default, FTDCR v6 with the environment variable ``HW_ROBOT=v6``.
Leave-one-pattern-family-out CV on ``train.csv`` only: the families are single segments (incl.
the tendon pulls and circles), pair12, pair13 and pair23. ``val.csv`` is not read here unless a
script is asked to (``--val``), so model choices can be made without looking at it.
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
torch.set_num_threads(1)

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc  # noqa: E402
from dacr_learn.hardware.learned import play_operator  # noqa: E402
from dacr_learn.hardware.metrics import offset_removed_rmse  # noqa: E402
from dacr_learn.hardware.recording import load_recording  # noqa: E402
from dacr_learn.hardware.study.benchmark import resolve_robot  # noqa: E402

ROBOT_NAME = os.environ.get("HW_ROBOT", "v4")   # HW_ROBOT=v6 runs a script on FTDCR v6's train.csv (it has no val)
DATA = ROOT / "data" / f"ftdcr_{ROBOT_NAME}"
ROBOT = ROOT / "configs" / "robots" / f"ftdcr_{ROBOT_NAME}_calibrated.yaml"
spec, smap, _ = resolve_robot(ROBOT, None, None, Path(tempfile.mkdtemp()), "mm")
train_rec = load_recording(DATA / "train.csv", spec)
x_tr, tip_tr = smap.displacements(spec, train_rec), train_rec.tip
m = spec.num_segments
radius = torch.tensor([s.radius for s in spec.segments], dtype=torch.float64)
_seg_of_joint = CalibratedCC(spec).encoder.segment_of_joint
passes = (torch.arange(m)[None, :] <= _seg_of_joint[:, None]).double()  # (N, m): joint i passes segment k


def family(label: str) -> str:
    if "tendon" in label or "_seg" in label:
        return "single"
    return "pair" + re.search(r"pair(\d\d)", label).group(1)


fam = np.array([family(label) for label in train_rec.labels])
FOLDS = ("single", "pair12", "pair13", "pair23")


def val_data():
    rec = load_recording(DATA / "val.csv", spec)
    return smap.displacements(spec, rec), rec.tip


def rmse(pred, tip) -> float:
    """Offset-removed tip RMSE [mm]."""
    return float(offset_removed_rmse(pred, tip)) * 1e3


def fit(x, tip) -> CalibratedCC:
    cc = CalibratedCC(spec)
    fit_cc(cc, x, tip)
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc


def bend_angles(cc, x):
    """(n, m) bending angle of each segment [rad] from the static CC encoder."""
    with torch.no_grad():
        return cc.encoder(x)[..., :2].norm(dim=-1) / radius


def tendon_play(x, w):
    """Scalar play (backlash) per column along the rows of x (n, N) with width w (n, N) or scalar."""
    return play_operator(x.unsqueeze(-1), w).squeeze(-1)


def cv_static_cc(transform) -> dict:
    """CV of the static CC model fitted on transformed commands ``transform(x_tr)`` (n, N)."""
    xt = transform(x_tr)
    folds = {}
    for f in FOLDS:
        tr = torch.from_numpy(fam != f)
        folds[f] = rmse(fit(xt[tr], tip_tr[tr])(xt[~tr]), tip_tr[~tr])
    return {"train": round(rmse(fit(xt, tip_tr)(xt), tip_tr), 3), "cv": round(float(np.mean(list(folds.values()))), 3),
            "folds": {k: round(v, 2) for k, v in folds.items()}}
