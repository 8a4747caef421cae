"""Averaging the tips of a Clarke-space model and a raw-servo model: do their errors cancel? (issue 12)

On the hidden v6 val the raw MLP (13.3 mm) beat every Clarke-space model (CC 14.7 mm); on v4 val the
order is reversed. This script asks, on training recordings alone, whether the two kinds of model
make different errors: every model named is fitted once per proxy fold (seed 0, the robot's CC variant
as the benchmark chooses it: v4 ``strain``, v6 ``base``), its test-row tips are kept, and every pair's
average tip is scored with the same offset-removed RMSE [mm] as the proxies.

One JSON line per robot and combination (single models and pairwise averages) appended to
results/model_average.jsonl: {"robot", "models", "extrap", "cv", "cv_folds"}.

~2 min per robot for singles → pairs, ~10 min with the family CV.

Numbers: docs/history/hardware.md, "2026-11-24: Fifth round: averaging two models' tips (tried, not adopted)".
Run from the repository root: python -m research.hardware_cv.model_average ROBOT MODELS [PROXIES]   (ROBOT: v4 | v6)
e.g.   python -m research.hardware_cv.model_average v6 cc,cc_compositional_residual,pretrained_raw,mlp_raw extrap
"""
import itertools
import json
import sys
import time

import numpy as np
import torch

from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.study.registry import build_model

from .common import RESULTS
from .folds import train_folds

OUT = RESULTS / "model_average.jsonl"


def fold_tips(model: str, fold, seed: int = 0) -> torch.Tensor:
    """(n_test, 3) [m] tips of ``model`` trained on the fold's rows, on its test rows."""
    net = build_model(model, fold.ctx, seed)
    net.fit(fold.ctx.train)
    with torch.no_grad():
        return net(fold.test).detach()


def run(robot: str, models: list[str], proxies: tuple[str, ...]) -> None:
    folds, variant = train_folds(robot, proxies)
    tips: dict[str, dict[str, dict[str, torch.Tensor]]] = {p: {} for p in proxies}   # proxy → fold → model → tips
    for model in models:
        start = time.perf_counter()
        for p, fs in folds.items():
            for f in fs:
                tips[p].setdefault(f.name, {})[model] = fold_tips(model, f)
        print(f"{robot} {model}: {time.perf_counter() - start:.0f} s", flush=True)
    combos = [(m,) for m in models] + list(itertools.combinations(models, 2))
    for combo in combos:
        line = {"robot": robot, "cc_variant": variant, "models": list(combo)}
        for p, fs in folds.items():
            per = {f.name: float(offset_removed_rmse(torch.stack([tips[p][f.name][m] for m in combo]).mean(0),
                                                      f.test.tip)) * 1e3 for f in fs}
            line[p] = round(float(np.mean(list(per.values()))), 4)
            if p == "cv":
                line["cv_folds"] = {k: round(v, 4) for k, v in per.items()}
        print(json.dumps(line), flush=True)
        with OUT.open("a") as fh:
            fh.write(json.dumps(line) + "\n")


def main() -> None:
    torch.set_num_threads(1)
    run(sys.argv[1], sys.argv[2].split(","), tuple(sys.argv[3].split(",")) if len(sys.argv) > 3 else ("extrap",))


if __name__ == "__main__":
    main()
