"""Clarke-space models that carry over between robots: support clamp and CC rehearsal (issue 12, item 3).

Scores variants of (e) ``cc_clarke_residual`` and (g) ``cc_clarke_residual_history`` with the
library's train-only selection proxies (:mod:`dacr_learn.hardware.study.selection`) on the training
recording of one robot. Variants are passed as constructor arguments, no library global is patched.
~15 s per fit on a quiet machine (minutes on a loaded one).

Numbers: docs/hardware_history.md, "2026-11-23: Carrying Clarke-space models over between robots"
(results/carry_over.jsonl).
Run from the repository root:

    python -m research.hardware_cv.carry_over ROBOT VARIANTS SEEDS [PROXIES]

ROBOT: v4 | v6 (configs/robots/ftdcr_<robot>_calibrated.yaml, data/ftdcr_<robot>/train.csv);
VARIANTS: comma-separated names of ``VARIANTS`` below or registered model names; SEEDS: 0,1;
PROXIES: extrap,cv (default both). One JSON line per variant on stdout. A variant written
``gate:NAME`` is trained once per fold and seed and scored at every support-gate width of
``GATE_WIDTHS`` (the gate acts on predictions only; ``inf``: no gate, 0: the CC model).
"""
import json
import sys

import numpy as np
import torch

from dacr_learn.hardware.learned import CCClarkeResidual, CCClarkeResidualHistory
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.registry import ModelInfo, model_info
from dacr_learn.hardware.study.selection import make_folds, proxy_masks, proxy_scores
from dacr_learn.robot import RobotSpec

from .common import ROOT, build_variant, variant_scores

REHEARSAL_SAMPLES = 1000
GATE_WIDTHS = (float("inf"), 4.0, 2.0, 1.0, 0.5, 0.25, 0.0)   # [training std of the Clarke features]


def variant(name: str, history: bool, support: bool, weight: float) -> ModelInfo:
    cls = CCClarkeResidualHistory if history else CCClarkeResidual

    def build(ctx, seed):
        synth = ctx.synthetic(seed, REHEARSAL_SAMPLES) if weight else None
        return cls(ctx.train, ctx.cc, support=support, rehearsal=synth, rehearsal_weight=weight)
    return ModelInfo(name, "?", build, "clarke", static=not history)


VARIANTS = {f"{base}{'_support' if s else ''}{f'_reh{w:g}' if w else ''}": variant(
    f"{base}{'_support' if s else ''}{f'_reh{w:g}' if w else ''}", base == "g", s, w)
    for base in ("e", "g") for s in (False, True) for w in (0.0, 0.1, 1.0, 10.0)}


def gate_scores(info: ModelInfo, folds: dict, seeds: list[int]) -> dict:
    """{proxy: {width: mean RMSE [mm]}} of one trained model per fold and seed, gated at every width."""
    out = {}
    for proxy, fs in folds.items():
        per = {w: [] for w in GATE_WIDTHS}
        for fold in fs:
            for seed in seeds:
                model = build_variant(info, fold.ctx, seed)
                model.fit(fold.ctx.train)
                for w in GATE_WIDTHS:
                    model.gate_width = None if w == float("inf") else w
                    with torch.no_grad():
                        per[w].append(float(offset_removed_rmse(model(fold.test), fold.test.tip)) * 1e3)
        out[proxy] = {str(w): round(float(np.mean(v)), 4) for w, v in per.items()}
    return out


def main() -> None:
    torch.set_num_threads(1)
    robot, names, seeds = sys.argv[1], sys.argv[2].split(","), [int(s) for s in sys.argv[3].split(",")]
    proxies = sys.argv[4].split(",") if len(sys.argv) > 4 else ["extrap", "cv"]
    spec = RobotSpec.from_yaml(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml")
    smap = ServoMap.from_yaml(ROOT / f"configs/robots/servo_maps/ftdcr_{robot}_calibrated.yaml")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)
    masks = proxy_masks(rec.labels)
    folds = {p: make_folds(rec, spec, smap, masks[p]) for p in proxies}
    for name in names:
        if name.startswith("gate:"):
            info = VARIANTS.get(name[5:]) or model_info(name[5:])
            scores = gate_scores(info, folds, seeds)
            print(json.dumps({"robot": robot, "model": name, "seeds": seeds, **scores}), flush=True)
            continue
        scores = variant_scores(VARIANTS[name], folds, seeds) if name in VARIANTS else proxy_scores(name, folds, seeds)
        print(json.dumps({"robot": robot, "model": name, **scores}), flush=True)


if __name__ == "__main__":
    main()
