"""Shared set-up of the hardware cross-validation experiments (research scripts, not library code).

FTDCR v4 by default, FTDCR v6 with the environment variable ``HW_ROBOT=v6``.
Leave-one-pattern-family-out CV on ``train.csv`` only: the families are single segments (incl.
the tendon pulls and circles), pair12, pair13 and pair23. ``val.csv`` is not read here unless a
script is asked to (``--val``), so model choices can be made without looking at it.

Importing this module reads nothing: :func:`setup` reads the robot and its ``train.csv`` on its
first call (cached), and the helpers below call it when they need the robot. :func:`variant_scores`
scores research variants (a ``ModelInfo`` the registry does not hold) as ``selection.proxy_scores``
scores registered models.
"""
from __future__ import annotations

import functools
import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.learned import play_operator
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import Recording, load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.benchmark import resolve_robot
from dacr_learn.hardware.study.registry import ModelInfo
from dacr_learn.hardware.study.selection import Fold, pattern_family, summarize_scores
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[2]
RESULTS = Path(__file__).resolve().parent / "results"
FOLDS = ("single", "pair12", "pair13", "pair23")


@dataclass(frozen=True)
class Setup:
    """The robot and its training recording, as the scripts use them."""

    robot: str                 # "v4" | "v6" (HW_ROBOT)
    data: Path                 # data/ftdcr_<robot>
    spec: RobotSpec
    smap: ServoMap
    train_rec: Recording
    x_tr: torch.Tensor         # (n, N) joint displacements of train.csv [m]
    tip_tr: torch.Tensor       # (n, 3) measured tips [m]
    fam: np.ndarray            # (n,) pattern family of each row: single, pair12, pair13, pair23
    radius: torch.Tensor       # (m,) nominal segment radii [m]
    passes: torch.Tensor       # (N, m): joint i passes segment k

    @property
    def m(self) -> int:
        return self.spec.num_segments


@functools.cache
def setup() -> Setup:
    """Read ``HW_ROBOT``'s calibrated robot, servo map and ``train.csv`` (once per process)."""
    torch.set_num_threads(1)
    robot = os.environ.get("HW_ROBOT", "v4")   # HW_ROBOT=v6 runs a script on FTDCR v6's train.csv (it has no val)
    data = ROOT / "data" / f"ftdcr_{robot}"
    yaml = ROOT / "configs" / "robots" / f"ftdcr_{robot}_calibrated.yaml"
    with tempfile.TemporaryDirectory() as tmp:  # only written to when calibrating from pulls, never here
        spec, smap, _ = resolve_robot(yaml, None, None, Path(tmp), "mm")
    train_rec = load_recording(data / "train.csv", spec)
    m = spec.num_segments
    seg_of_joint = CalibratedCC(spec).encoder.segment_of_joint
    # the families of the original family() (single: "tendon" or "_seg" in the label, else pair<jk>), which
    # equal the library's selection.pattern_family on both robots' train labels
    fam = np.array([pattern_family(label) for label in train_rec.labels])
    return Setup(robot=robot, data=data, spec=spec, smap=smap, train_rec=train_rec,
                 x_tr=smap.displacements(spec, train_rec), tip_tr=train_rec.tip, fam=fam,
                 radius=torch.tensor([s.radius for s in spec.segments], dtype=torch.float64),
                 passes=(torch.arange(m)[None, :] <= seg_of_joint[:, None]).double())


def val_data():
    """(x, tip) of the robot's val.csv (FTDCR v4; v6 has no val in the repository)."""
    d = setup()
    rec = load_recording(d.data / "val.csv", d.spec)
    return d.smap.displacements(d.spec, rec), rec.tip


def rmse(pred, tip) -> float:
    """Offset-removed tip RMSE [mm]."""
    return float(offset_removed_rmse(pred, tip)) * 1e3


def fit(x, tip) -> CalibratedCC:
    cc = CalibratedCC(setup().spec)
    fit_cc(cc, x, tip)
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc


def bend_angles(cc, x):
    """(n, m) bending angle of each segment [rad] from the static CC encoder."""
    with torch.no_grad():
        return cc.encoder(x)[..., :2].norm(dim=-1) / setup().radius


def tendon_play(x, w):
    """Scalar play (backlash) per column along the rows of x (n, N) with width w (n, N) or scalar."""
    return play_operator(x.unsqueeze(-1), w).squeeze(-1)


def cv_static_cc(transform) -> dict:
    """CV of the static CC model fitted on transformed commands ``transform(x_tr)`` (n, N)."""
    d = setup()
    xt = transform(d.x_tr)
    folds = {}
    for f in FOLDS:
        tr = torch.from_numpy(d.fam != f)
        folds[f] = rmse(fit(xt[tr], d.tip_tr[tr])(xt[~tr]), d.tip_tr[~tr])
    return {"train": round(rmse(fit(xt, d.tip_tr)(xt), d.tip_tr), 3),
            "cv": round(float(np.mean(list(folds.values()))), 3), "folds": {k: round(v, 2) for k, v in folds.items()}}


def build_variant(info: ModelInfo, ctx, seed: int) -> torch.nn.Module:
    """A fresh, untrained model of ``info`` (registered or a research variant), torch seeded with ``seed``
    first, as ``registry.build_model`` builds registered models."""
    torch.manual_seed(seed)
    return info.build(ctx, seed)


def variant_scores(info: ModelInfo, folds: dict[str, list[Fold]], seeds: Sequence[int]) -> dict:
    """``selection.proxy_scores`` for a research variant: {proxy: mean RMSE [mm], proxy + "_folds", "seeds",
    "seconds"}, each fold's model trained on its rows and scored (offset removed) on its test rows."""
    start = time.perf_counter()
    seeds = list(seeds)[:1] if info.deterministic else list(seeds)
    scores: dict[str, dict[str, list[float]]] = {}
    for proxy, fs in folds.items():
        scores[proxy] = {}
        for fold in fs:
            scores[proxy][fold.name] = []
            for seed in seeds:
                model = build_variant(info, fold.ctx, seed)
                model.fit(fold.ctx.train)
                with torch.no_grad():
                    scores[proxy][fold.name].append(rmse(model(fold.test), fold.test.tip))
    return summarize_scores(scores, seeds, time.perf_counter() - start)
