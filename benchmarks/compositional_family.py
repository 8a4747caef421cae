"""Compositional vs monolithic FK on the heterogeneous robot family, and transfer across geometries.

    .venv/bin/python benchmarks/compositional_family.py [--seeds 0 1] [--out docs/compositional/family]

For every robot (configs/robots/hetero_*.yaml and tdcr_3seg_coupled.yaml) and seed, the user's command
is run unchanged but for the robot and the seed:

- ``compositional`` : ``train.py fit --config configs/fk_tdcr3_compositional.yaml --data.robot R``
  (strain units, the default);
- ``compositional_metric``: the same with ``--model.init_args.units metric`` (features in metres, one
  translation scale: the model before geometry-aware units);
- ``monolithic``: ``train.py fit --config configs/fk_tdcr3.yaml --data.robot R``.

The test-split error comes from each run's ``metrics.json``; the wall time is the whole command's (data
generation, training, validation and test). Then the strain-unit network trained on the first robot
(per seed) is transferred unchanged (:func:`dacr_learn.compositional.transfer`) to every other robot and
evaluated on 10 000 fresh samples of it. Writes ``<out>.csv`` (one row per run), ``<out>_transfer.csv``
and ``<out>.md`` (mean ± sample std over seeds). ``--variants compositional compositional_metric --keep
monolithic`` reruns the compositional models and keeps the monolithic rows of ``<out>.csv``.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from dacr_learn import load_model, runs
from dacr_learn.compositional import transfer
from dacr_learn.data import generate
from dacr_learn.metrics import pose_errors
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]

ROBOTS = ("hetero_3seg_coupled", "hetero_2seg_coupled", "hetero_4seg_types", "hetero_5seg_coupled",
          "tdcr_3seg_coupled")
VARIANTS = {"compositional": ("configs/fk_tdcr3_compositional.yaml", []),
            "compositional_metric": ("configs/fk_tdcr3_compositional.yaml", ["--model.init_args.units", "metric"]),
            "monolithic": ("configs/fk_tdcr3.yaml", [])}


def train(robot: str, variant: str, seed: int, runs_dir: Path) -> dict:
    config, extra = VARIANTS[variant]
    name = f"{robot}_{variant}_s{seed}"
    cmd = [sys.executable, "train.py", "fit", "--config", config, "--data.robot", f"configs/robots/{robot}.yaml",
           "--seed_everything", str(seed), "--data.seed", str(seed), "--runs_dir", str(runs_dir),
           "--run_name", name, "--trainer.enable_progress_bar", "false", *extra]
    start = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    run = runs.versions(runs_dir / name)[-1]
    metrics = json.loads((run / "metrics.json").read_text())
    return {"robot": robot, "variant": variant, "seed": seed, "pos_pct": metrics["pos_err_mean_pct"],
            "pos_mm": metrics["pos_err_mean_mm"], "rot_deg": metrics["rot_err_mean_deg"], "wall_s": wall,
            "run": str(run)}


def transfer_error(run: str, robot: str, seed: int) -> dict | None:
    """Error of the network of ``run`` moved to ``robot``; None where transfer refuses (a feature the source
    never varied, e.g. twist)."""
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / f"{robot}.yaml")
    try:
        model = transfer(load_model(run, torch.float64), spec).eval()
    except ValueError as exc:
        print(f"transfer to {robot}: {exc}")
        return None
    data = generate(spec, 10_000, seed=10_000 + seed, dtype=torch.float64)
    with torch.no_grad():
        err = pose_errors(model(data["q"]), data["pose"])
    return {"robot": robot, "seed": seed, "pos_pct": 100 * err["pos_err"].mean().item() / spec.total_length,
            "rot_deg": torch.rad2deg(err["rot_err"]).mean().item()}


def mean_std(values: list[float], fmt: str) -> str:
    if len(values) < 2:
        return format(values[0], fmt)
    return f"{format(statistics.mean(values), fmt)} ± {format(statistics.stdev(values), fmt)}"


def summary(rows: list[dict], moved: list[dict], source: str) -> str:
    lines = ["| robot | model | test position error [% of length] | rotation [°] | wall time [s] |",
             "|---|---|---|---|---|"]
    for robot in dict.fromkeys(r["robot"] for r in rows):
        for variant in VARIANTS:
            sel = [r for r in rows if r["robot"] == robot and r["variant"] == variant]
            if sel:
                lines.append(f"| {robot} | {variant} | {mean_std([r['pos_pct'] for r in sel], '.4f')} | "
                             f"{mean_std([r['rot_deg'] for r in sel], '.4f')} | "
                             f"{mean_std([r['wall_s'] for r in sel], '.0f')} |")
    lines += ["", f"Transfer: the compositional network trained on {source}, unchanged, on other robots "
              "(10 000 fresh samples each)", "", "| target robot | position error [% of length] | rotation [°] |",
              "|---|---|---|"]
    for robot in dict.fromkeys(r["robot"] for r in moved):
        sel = [r for r in moved if r["robot"] == robot]
        lines.append(f"| {robot} | {mean_std([r['pos_pct'] for r in sel], '.4f')} | "
                     f"{mean_std([r['rot_deg'] for r in sel], '.4f')} |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--robots", nargs="+", default=list(ROBOTS), help="the first is the transfer source")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "compositional_family")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "compositional" / "family")
    parser.add_argument("--keep", nargs="+", default=[], choices=list(VARIANTS),
                        help="variants not rerun: their rows are kept from <out>.csv (their config unchanged)")
    args = parser.parse_args(argv)
    kept = []
    if args.keep:
        with args.out.with_suffix(".csv").open(newline="") as f:
            numbers = ("pos_pct", "pos_mm", "rot_deg", "wall_s")
            kept = [{**r, "seed": int(r["seed"]), **{k: float(r[k]) for k in numbers}}
                    for r in csv.DictReader(f) if r["variant"] in args.keep and r["variant"] not in args.variants]
    rows, moved = [], []
    for seed in args.seeds:
        for robot in args.robots:
            for variant in args.variants:
                rows.append(train(robot, variant, seed, args.runs_dir))
                print(f"{robot:22s} {variant:22s} seed {seed}: {rows[-1]['pos_pct']:.4f} %  "
                      f"{rows[-1]['rot_deg']:.4f}°  {rows[-1]['wall_s']:.0f} s", flush=True)
        source = next((r["run"] for r in rows if r["seed"] == seed and r["robot"] == args.robots[0]
                       and r["variant"] == "compositional"), None)
        if source is not None:
            moved += [e for robot in args.robots[1:] if (e := transfer_error(source, robot, seed)) is not None]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows += kept
    write_csv(args.out.with_suffix(".csv"), rows)
    if moved:
        write_csv(args.out.parent / f"{args.out.name}_transfer.csv", moved)
    text = summary(rows, moved, args.robots[0])
    args.out.with_suffix(".md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
