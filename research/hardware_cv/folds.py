"""Proxy folds of a robot's training recording with its chosen CC variant (shared by the issue-12 scripts
``model_average`` and ``compositional_history``). Reads train.csv only, never val, and only when called."""
from __future__ import annotations

import tempfile
from pathlib import Path

from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.study.benchmark import resolve_robot
from dacr_learn.hardware.study.selection import CC_VARIANTS, Fold, choose_cc_variant, make_folds, proxy_masks

from .common import ROOT


def train_folds(robot: str, proxies: tuple[str, ...]) -> tuple[dict[str, list[Fold]], str]:
    """({proxy: folds}, CC variant) of FTDCR ``robot`` ("v4" | "v6"): the calibrated robot, the CC variant the
    benchmark would choose (its singles → pairs score), and every proxy's folds with that CC model refitted."""
    with tempfile.TemporaryDirectory() as tmp:    # only written to when calibrating from pulls, never here
        spec, smap, _ = resolve_robot(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml", None, None,
                                      Path(tmp), "mm")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)      # train only, never val
    variant, _ = choose_cc_variant(rec, spec, smap)
    masks = proxy_masks(list(rec.labels), proxies)
    return {p: make_folds(rec, spec, smap, masks[p], CC_VARIANTS[variant]) for p in proxies}, variant
