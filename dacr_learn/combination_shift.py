"""Combination shift and segment transfer of learned FK, on synthetic data (docs/compositional.md).

Combination shift (the synthetic twin of the real robots' regime shift): train where at most
``max_bending`` segments bend (the others straight, ρ = 0; every segment's β, α still vary), test
on held-out samples of that regime and on samples where every segment bends. Models (equal
optimisation steps): compositional (per-segment network, Clarke features), monolithic Clarke,
monolithic raw joints. Transfer: a compositional model trained on a 2-segment robot runs,
unchanged, a 3-segment robot of the same segments (:func:`compositional.transfer`).

    python -m dacr_learn.combination_shift --out runs/combination_shift              # both studies
    python -m dacr_learn.combination_shift --out runs/x --study shift --seeds 0 1 2 --steps 2000
    python -m dacr_learn.combination_shift --out runs/x --quick                      # a smoke run (seconds)

Writes ``<out>/results.csv`` (one row per model, seed and test set), ``<out>/summary.json`` and
``<out>/summary.md`` (mean ± std over seeds, ratio all-bending / held-out).
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

import lightning.pytorch as pl
import torch
from torch import Tensor

from .ablation.runner import evaluate, quiet_lightning, train_steps
from .compositional import transfer
from .console import run_cli
from .data import generate
from .robot import RobotSpec
from .training import FKModule

ROOT = Path(__file__).resolve().parents[1]
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
TRANSFER = (ROOT / "configs" / "robots" / "tdcr_2seg_equal.yaml", ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml")
COMPOSITIONAL = {"structure": "compositional", "features": "clarke", "rotation": "twist", "width": 64, "depth": 3,
                 "lr": 1e-2, "rot_weight": 0.1}
MONOLITHIC = {"structure": "monolithic", "rotation": "6d", "width": 256, "depth": 3, "lr": 2e-3, "rot_weight": 0.1}
MODELS = {"compositional": COMPOSITIONAL, "monolithic_clarke": {**MONOLITHIC, "features": "clarke"},
          "monolithic_raw": {**MONOLITHIC, "features": "raw"}}
COLUMNS = ["study", "model", "seed", "test", "pos_err_mean_mm", "pos_err_mean_pct", "rot_err_mean_deg",
           "steps", "train_seconds"]


def combination_split(spec: RobotSpec, n_train: int, n_test: int, seed: int,
                      max_bending: int = 2) -> dict[str, dict[str, Tensor]]:
    """{"train", "heldout", "all_bending"}: the training regime (at most ``max_bending`` segments bend),
    held-out samples of that regime and samples where every segment bends; disjoint seeds."""
    if not 0 <= max_bending < spec.num_segments:
        raise ValueError(f"max_bending: expected 0 … {spec.num_segments - 1} (fewer than the "
                         f"{spec.num_segments} segments, or the test regime is the training one), got {max_bending}")
    return {"train": generate(spec, n_train, seed, max_bending=max_bending),
            "heldout": generate(spec, n_test, 10_000 + seed, max_bending=max_bending),
            "all_bending": generate(spec, n_test, 20_000 + seed)}


def train_fk(spec: RobotSpec, data: dict[str, Tensor], params: dict, steps: int, batch_size: int,
             seed: int) -> tuple[FKModule, float]:
    """An FKModule with ``params`` trained for ``steps`` steps on ``data`` (tip poses); (module, seconds)."""
    quiet_lightning()
    pl.seed_everything(seed, verbose=False)
    module = FKModule(robot=spec.to_dict(), **params)
    seconds = train_steps(module, data, steps, batch_size, seed)
    return module.eval(), seconds


def _row(study: str, model: str, seed: int, test: str, summary: dict, steps: int, seconds: float) -> dict:
    return {"study": study, "model": model, "seed": seed, "test": test, "steps": steps,
            "train_seconds": round(seconds, 1),
            **{k: round(summary[k], 6) for k in ("pos_err_mean_mm", "pos_err_mean_pct", "rot_err_mean_deg")}}


def shift_study(seeds: list[int], steps: int, n_train: int, n_test: int, batch_size: int = 512,
                models: dict[str, dict] | None = None, robot: Path = ROBOT) -> list[dict]:
    """Rows of the combination-shift study (every model × seed × {heldout, all_bending})."""
    spec, rows = RobotSpec.from_yaml(robot), []
    for seed in seeds:
        split = combination_split(spec, n_train, n_test, seed)
        for name, params in (models or MODELS).items():
            module, seconds = train_fk(spec, split["train"], params, steps, batch_size, seed)
            rows += [_row("shift", name, seed, test, evaluate(module, "fk", split[test]), steps, seconds)
                     for test in ("heldout", "all_bending")]
    return rows


def transfer_study(seeds: list[int], steps: int, n_train: int, n_test: int, batch_size: int = 512,
                   robots: tuple[Path, Path] = TRANSFER) -> list[dict]:
    """Rows of the transfer study: compositional model trained on robots[0], tested there and, through
    :func:`compositional.transfer` (network unchanged), on robots[1]."""
    source, target = (RobotSpec.from_yaml(r) for r in robots)
    rows = []
    for seed in seeds:
        module, seconds = train_fk(source, generate(source, n_train, seed), COMPOSITIONAL, steps, batch_size, seed)
        moved = FKModule(robot=target.to_dict(), **COMPOSITIONAL)
        moved.model = transfer(module.model, target)
        rows.append(_row("transfer", "compositional", seed, f"{source.name} (trained)",
                         evaluate(module, "fk", generate(source, n_test, 20_000 + seed)), steps, seconds))
        rows.append(_row("transfer", "compositional", seed, f"{target.name} (transferred)",
                         evaluate(moved, "fk", generate(target, n_test, 20_000 + seed)), steps, seconds))
    return rows


def summarize_rows(rows: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """{study/model: {test: {metric: mean, metric_std: std, n}}} over seeds, plus shift ratios."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((f"{r['study']}/{r['model']}", r["test"]), []).append(r)
    out: dict[str, dict] = {}
    for (key, test), rs in groups.items():
        stats = {"n": len(rs)}
        for m in ("pos_err_mean_mm", "pos_err_mean_pct", "rot_err_mean_deg"):
            values = [float(r[m]) for r in rs]
            stats[m], stats[m + "_std"] = statistics.mean(values), statistics.stdev(values) if len(values) > 1 else 0.0
        out.setdefault(key, {})[test] = stats
    for tests in out.values():
        if {"heldout", "all_bending"} <= tests.keys():
            tests["ratio_all_bending_to_heldout"] = {
                m: tests["all_bending"][m] / tests["heldout"][m] for m in ("pos_err_mean_mm", "rot_err_mean_deg")}
    return out


def markdown(summary: dict) -> str:
    lines = ["| study / model | test | position error [mm] | [% of length] | rotation error [°] |",
             "|---|---|---|---|---|"]
    for key, tests in summary.items():
        for test, s in tests.items():
            if test.startswith("ratio"):
                lines.append(f"| {key} | **all-bending / held-out** | **{s['pos_err_mean_mm']:.2f}×** | | "
                             f"**{s['rot_err_mean_deg']:.2f}×** |")
            else:
                lines.append(f"| {key} | {test} (n={s['n']}) | {s['pos_err_mean_mm']:.4f} ± "
                             f"{s['pos_err_mean_mm_std']:.4f} | {s['pos_err_mean_pct']:.4f} | "
                             f"{s['rot_err_mean_deg']:.4f} ± {s['rot_err_mean_deg_std']:.4f} |")
    return "\n".join(lines) + "\n\n(mean ± sample std over seeds)\n"


def write(rows: list[dict], out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    summary = summarize_rows(rows)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    (out / "summary.md").write_text(markdown(summary))
    return summary


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.combination_shift", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--study", choices=("shift", "transfer", "both"), default="both")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=2000, help="optimisation steps of every training (equal for all)")
    p.add_argument("--n_train", type=int, default=50_000)
    p.add_argument("--n_test", type=int, default=5_000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true", help="tiny smoke run: 1 seed, 40 steps, small data")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.quick:
        a.seeds, a.steps, a.n_train, a.n_test = [0], 40, 2000, 500
    rows = []
    if a.study in ("shift", "both"):
        rows += shift_study(a.seeds, a.steps, a.n_train, a.n_test)
    if a.study in ("transfer", "both"):
        rows += transfer_study(a.seeds, a.steps, a.n_train, a.n_test)
    summary = write(rows, a.out)
    print(markdown(summary))
    return summary


if __name__ == "__main__":
    sys.exit(run_cli(main))
