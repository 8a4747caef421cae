"""Clarke vs raw IK of the 3-segment coupled robot from one train.py config, at several training sizes.

Every cell (features, n_train, seed) is one ``train.py fit`` of the same config, changed only by
``--model.init_args.features``, ``--data.n_train`` and the seed (``--seed_everything`` and ``--data.seed``:
initialisation and dataset), run one after another with one torch thread. Numbers: docs/history/ablation.md,
"One configuration for every training size". From the repository root:

    python -m research.ik_tdcr3_grid --n-train 100000 10000 1000 --seeds 0 1 --out runs/ik_tdcr3_grid

Writes ``results.csv`` (one row per training: the test metrics of train.py's metrics.json, the last
validation metrics and the fit time; a finished cell is skipped on a rerun) and ``summary.md`` (mean ± std
over seeds) under ``--out``; the runs themselves go to ``<out>/runs``. ``--set KEY=VALUE`` adds train.py
overrides to every cell (for exploring on the validation split; a grid with overrides writes its own files).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from lightning.pytorch import Callback

METRICS = ("pos_err_mean_mm", "rot_err_mean_deg", "out_of_limits_pct")
COLUMNS = ["features", "n_train", "seed", *(f"test_{m}" for m in METRICS), *(f"val_{m}" for m in METRICS),
           "train_seconds", "overrides"]


class ValidationLog(Callback):
    """Appends every validation's metrics (with the step) to ``val.jsonl`` in the run folder."""

    def on_validation_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        row = {"step": trainer.global_step,
               **{k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}}
        with (Path(trainer.default_root_dir) / "val.jsonl").open("a") as f:
            f.write(json.dumps(row) + "\n")


def run_cell(config: str, features: str, n_train: int, seed: int, out: Path, overrides: list[str]) -> dict:
    name = f"{features}_n{n_train}_s{seed}"
    root = out / "runs" / name
    before = set(root.glob("version_*"))
    cmd = [sys.executable, "train.py", "fit", "--config", config, "--model.init_args.features", features,
           "--data.n_train", str(n_train), "--seed_everything", str(seed), "--data.seed", str(seed),
           "--runs_dir", str(out / "runs"), "--run_name", name, "--num_threads", "1",
           "--trainer.enable_progress_bar", "false", "--trainer.callbacks+=research.ik_tdcr3_grid.ValidationLog"]
    for item in overrides:
        key, _, value = item.partition("=")
        cmd += [f"--{key}", value]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    (run,) = set(root.glob("version_*")) - before
    test = json.loads((run / "metrics.json").read_text())
    val = [json.loads(line) for line in (run / "val.jsonl").read_text().splitlines()]
    return {"features": features, "n_train": n_train, "seed": seed,
            **{f"test_{m}": test[m] for m in METRICS}, **{f"val_{m}": val[-1][f"val/{m}"] for m in METRICS},
            "train_seconds": round(test["train_seconds"]), "overrides": " ".join(overrides)}


def mean_std(values: list[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.3g}"
    return f"{statistics.mean(values):.3g} ± {statistics.stdev(values):.2g}"


def summary(rows: list[dict]) -> str:
    lines = ["| features | n_train | seeds | test pos [mm] | test rot [deg] | test out of limits [%] | "
             "val pos [mm] | fit time [s] |", "|---|---|---|---|---|---|---|---|"]
    cells: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        cells.setdefault((r["features"], int(r["n_train"])), []).append(r)
    for (features, n), group in sorted(cells.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        cols = [mean_std([float(r[key]) for r in group]) for key in
                ("test_pos_err_mean_mm", "test_rot_err_mean_deg", "test_out_of_limits_pct", "val_pos_err_mean_mm",
                 "train_seconds")]
        lines.append(f"| {features} | {n} | {len(group)} | " + " | ".join(cols) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/ik_tdcr3.yaml")
    p.add_argument("--n-train", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--features", nargs="+", default=["clarke", "raw"])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="train.py overrides for every cell")
    p.add_argument("--out", type=Path, default=Path("runs/ik_tdcr3_grid"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "results.csv"
    rows = list(csv.DictReader(path.open())) if path.is_file() else []
    overrides = " ".join(args.set)
    for seed in args.seeds:
        for n in args.n_train:
            for features in args.features:
                if any((r["features"], int(r["n_train"]), int(r["seed"]), r["overrides"]) ==
                       (features, n, seed, overrides) for r in rows):
                    continue
                row = run_cell(args.config, features, n, seed, args.out, args.set)
                print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
                      flush=True)
                new = not path.is_file()
                with path.open("a", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=COLUMNS)
                    if new:
                        w.writeheader()
                    w.writerow(row)
                rows.append(row)
                (args.out / "summary.md").write_text(summary([r for r in rows if r["overrides"] == overrides]))


if __name__ == "__main__":
    main()
