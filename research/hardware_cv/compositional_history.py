"""The compositional model (j) with each segment's motion memory as extra input: hysteresis on (j)? (issue 12)

On v4 the history model (g) beats its static twin (e) on val (5.62 vs 6.30 mm); on v6 the Clarke-residual
structure of (e)/(g) extrapolates badly while (j) is the best deployable model. This variant keeps (j)'s
structure and feeds its shared per-segment network, besides segment k's standardised features (and
context), segment k's play memory (ρ_k − play(ρ_k))/PLAY_WIDTH (2 values, the input (g) adds).

Rule, written down before any score of it was computed: it becomes a registry candidate only if its
singles → pairs score (seed 0, the robot's CC variant as the benchmark chooses it) is ≥ 0.2 mm below (j)'s
on one robot and not more than 0.1 mm above on the other.

The variant is now the library's ``CCCompositionalResidual(history=True)``, registry (k)
``cc_compositional_history`` (it passed: results/compositional_history.jsonl).
One JSON line per model and proxy appended to results/compositional_history.jsonl; ~2 min per robot
(singles → pairs), ~3 min with the CV.

Numbers: docs/history/hardware.md, "2026-11-24: The compositional model with memory (k)".
Run from the repository root: python -m research.hardware_cv.compositional_history ROBOT [PROXIES]
(ROBOT: v4 | v6; PROXIES: extrap,cv, default extrap)
"""
import json
import sys
import time

import torch

from dacr_learn.hardware.study.selection import proxy_scores

from .common import RESULTS
from .folds import train_folds

OUT = RESULTS / "compositional_history.jsonl"
MODELS = ("cc_compositional_residual", "cc_compositional_history")


def run(robot: str, proxies: tuple[str, ...]) -> None:
    folds, variant = train_folds(robot, proxies)
    for name in MODELS:
        start = time.perf_counter()
        scores = proxy_scores(name, folds, [0])
        line = {"robot": robot, "cc_variant": variant, "model": name,
                **{p: scores[p] for p in proxies}, **{p + "_folds": scores[p + "_folds"] for p in proxies},
                "seconds": round(time.perf_counter() - start, 1)}
        print(json.dumps(line), flush=True)
        with OUT.open("a") as fh:
            fh.write(json.dumps(line) + "\n")


def main() -> None:
    torch.set_num_threads(1)
    run(sys.argv[1], tuple(sys.argv[2].split(",")) if len(sys.argv) > 2 else ("extrap",))


if __name__ == "__main__":
    main()
