"""Clarke-space models that carry over between robots: support clamp and CC rehearsal (issue 12, item 3).

Scores variants of (e) ``cc_clarke_residual`` and (g) ``cc_clarke_residual_history`` with the
library's train-only selection proxies (:mod:`dacr_learn.hardware.study.selection`) on the training
recording of one robot. Variants are passed as constructor arguments, no library global is patched.
~15 s per fit on a quiet machine (minutes on a loaded one). The options (support clamp, CC rehearsal,
fallback gate) left the library on 2026-11-25 (no registered model used them); :class:`CarryOver` here
keeps them for this script, as the library had them.

Numbers: docs/history/hardware.md, "2026-11-23: Carrying Clarke-space models over between robots"
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

from dacr_learn.hardware.learned import RESIDUAL_RHO_SCALE, CCClarkeResidual, CCClarkeResidualHistory, Split
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.registry import ModelInfo
from dacr_learn.hardware.study.selection import make_folds, proxy_masks, proxy_scores
from dacr_learn.robot import RobotSpec

from .common import ROOT, build_variant, variant_scores

REHEARSAL_SAMPLES = 1000
GATE_WIDTHS = (float("inf"), 4.0, 2.0, 1.0, 0.5, 0.25, 0.0)   # [training std of the Clarke features]


class CarryOver:
    """Options of a CC Clarke-residual model (mixed into CCClarkeResidual or its history variant):

    - ``support``: the network sees ρ⁽ᵏ⁾ radially clamped to the largest bend of segment k in the training
      split, ρ⁽ᵏ⁾·min(1, r_k/‖ρ⁽ᵏ⁾‖): beyond the training range the correction stays at its boundary value.
    - ``rehearsal`` (a synthetic split of the calibrated CC robot, all segments at once) with weight
      ``rehearsal_weight``: the loss also asks the corrected model to reproduce the CC model's tips there.
    - ``gate_width`` τ: the correction times exp(−(δ/τ)²), δ the distance of the command's Clarke features
      (all segments, in units of their training std) to the nearest training row; training rows have δ = 0
      and the gate acts on predictions only (τ = 0: the CC model).
    """

    def set_options(self, support: bool = False, rehearsal: Split | None = None, rehearsal_weight: float = 0.0,
                    gate_width: float | None = None):
        self.support, self.rehearsal, self.rehearsal_weight, self.gate_width = (support, rehearsal,
                                                                                  rehearsal_weight, gate_width)
        self.training_fit = False
        return self

    def fit_normalization(self, train: Split) -> None:
        super().fit_normalization(train)
        self.rho_max = train.features[..., :2].float().norm(dim=-1).amax(0)         # (m,) [m]
        self.train_clarke = train.clarke / self.rho_std                            # (n_train, 2m)

    def support_gate(self, split: Split) -> torch.Tensor:
        if self.gate_width == 0:
            return split.clarke.new_zeros(len(split))
        distance = torch.cdist(split.clarke / self.rho_std, self.train_clarke).amin(-1)
        return torch.exp(-(distance / self.gate_width).pow(2))

    def corrected_features(self, split: Split) -> torch.Tensor:
        rho = split.features[..., :2].float()
        rho_in = rho
        if self.support:
            rho_in = rho * (self.rho_max.unsqueeze(-1) / rho.norm(dim=-1, keepdim=True).clamp_min(1e-12)).clamp(max=1.0)
        parts = [rho_in / self.rho_std] + ([split.memory.float()] if self.history else [])
        delta = self.net(torch.cat(parts + [self.onehot.expand(*rho.shape[:-1], -1)], -1)) * RESIDUAL_RHO_SCALE
        if self.gate_width is not None and not self.training_fit:
            delta = delta * self.support_gate(split)[:, None, None]
        features = split.features.float()
        return torch.cat([features[..., :2] + delta, features[..., 2:]], -1)

    def objective(self, train: Split) -> torch.Tensor:
        loss = super().objective(train)
        if self.rehearsal is not None and self.rehearsal_weight != 0:
            loss = loss + self.rehearsal_weight * (self(self.rehearsal) - self.rehearsal.tip).pow(2).mean() / 1e-6
        return loss

    def fit(self, train: Split) -> None:
        self.training_fit = True
        try:
            super().fit(train)
        finally:
            self.training_fit = False


class CarryOverResidual(CarryOver, CCClarkeResidual):
    pass


class CarryOverResidualHistory(CarryOver, CCClarkeResidualHistory):
    pass


def variant(name: str, history: bool, support: bool, weight: float) -> ModelInfo:
    cls = CarryOverResidualHistory if history else CarryOverResidual

    def build(ctx, seed):
        synth = ctx.synthetic(seed, REHEARSAL_SAMPLES) if weight else None
        return cls(ctx.cc).set_options(support=support, rehearsal=synth, rehearsal_weight=weight)
    return ModelInfo(name, build, "clarke", static=not history)


VARIANTS = {f"{base}{'_support' if s else ''}{f'_reh{w:g}' if w else ''}": variant(
    f"{base}{'_support' if s else ''}{f'_reh{w:g}' if w else ''}", base == "g", s, w)
    for base in ("e", "g") for s in (False, True) for w in (0.0, 0.1, 1.0, 10.0)}


GATED = {"cc_clarke_residual": "e", "cc_clarke_residual_history": "g"}   # registered names → their variant here


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
            info = VARIANTS[GATED.get(name[5:], name[5:])]
            scores = gate_scores(info, folds, seeds)
            print(json.dumps({"robot": robot, "model": name, "seeds": seeds, **scores}), flush=True)
            continue
        scores = variant_scores(VARIANTS[name], folds, seeds) if name in VARIANTS else proxy_scores(name, folds, seeds)
        print(json.dumps({"robot": robot, "model": name, **scores}), flush=True)


if __name__ == "__main__":
    main()
