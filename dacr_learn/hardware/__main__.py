"""``python -m dacr_learn.hardware --data DIR --robot YAML --out runs/NAME``

Calibrates (when the robot YAML has no servo map), fits the CC model, trains and evaluates all
tip models on ``DIR/<train>`` / ``DIR/<val>``, and writes into ``--out``: results.json,
results.md (table), val_predictions.csv (first seed, mm), val_tip_paths.png and
val_tip_paths.rrd (Rerun).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch

from .benchmark import CLARKE_MODELS, MODELS, STATIC_MODELS, load_setup, markdown_table, run_benchmark


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m dacr_learn.hardware", description=__doc__.split("\n\n")[1])
    ap.add_argument("--data", type=Path, required=True, help="folder with the recordings")
    ap.add_argument("--robot", type=Path, required=True, help="robot YAML (with servo_maps/<name> next to it, or nominal)")
    ap.add_argument("--out", type=Path, required=True, help="run folder to write")
    ap.add_argument("--train", default="train.csv", help="training recording, relative to --data")
    ap.add_argument("--val", default="val.csv", help="validation recording, relative to --data")
    ap.add_argument("--pulls", default="tendon_pull.csv",
                    help="single-pull recording for calibration when the robot has no servo map")
    ap.add_argument("--servo-map", type=Path, help="servo map YAML (default: servo_maps/<robot file name> next to the robot)")
    ap.add_argument("--units", default="mm", choices=["mm", "m"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 is fastest for these sizes)")
    ap.add_argument("--no-visuals", action="store_true", help="skip the PNG and the Rerun recording")
    return ap.parse_args(argv)


def write_predictions(path: Path, rec, preds: dict) -> None:
    """CSV: label, measured tip and each model's prediction (first seed) on val, in mm."""
    names = list(preds)
    cols = ["pattern_label", "tip_x", "tip_y", "tip_z"] + [f"{n}_{a}" for n in names for a in "xyz"]
    rows = [",".join(cols)]
    for i, label in enumerate(rec.labels):
        values = rec.tip[i].tolist() + [v for n in names for v in preds[n][i].tolist()]
        rows.append(",".join([label] + [f"{v * 1e3:.4f}" for v in values]))
    path.write_text("\n".join(rows) + "\n")


def best_model(results: dict, candidates: tuple[str, ...]) -> str | None:
    """The candidate with the lowest mean val RMSE, or None."""
    names = [k for k in results if k in candidates]
    return min(names, key=lambda k: results[k]["val"]["rmse_mm"]["mean"]) if names else None


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    setup = load_setup(args.robot, args.data / args.train, args.data / args.val, args.out,
                       args.servo_map, args.data / args.pulls, args.units)
    print(f"CC fit on {len(setup.train_rec)} rows: {setup.cc_fit['rms_m'] * 1e3:.2f} mm rms "
          f"({setup.cc_fit['seconds']:.1f} s); parameters {setup.cc_fit['parameters']}")
    results, preds = run_benchmark(setup, tuple(args.models), tuple(args.seeds))
    best = best_model(results, CLARKE_MODELS)
    best_static = best_model(results, tuple(m for m in CLARKE_MODELS if m in STATIC_MODELS))
    report = {"command": "python -m dacr_learn.hardware " + " ".join(sys.argv[1:] if argv is None else argv),
              "robot": setup.spec.to_dict(), "train": str(args.data / args.train), "val": str(args.data / args.val),
              "rows": {"train": len(setup.train_rec), "val": len(setup.val_rec)},
              "calibration": setup.calibration, "cc_fit": setup.cc_fit, "models": results,
              "best_clarke_model": best, "best_static_clarke_model": best_static, "seconds_total": time.perf_counter() - start,
              "environment": {"torch": torch.__version__, "threads": args.threads, "python": platform.python_version()}}
    (args.out / "results.json").write_text(json.dumps(report, indent=1))
    (args.out / "results.md").write_text(markdown_table(results) + "\n")
    write_predictions(args.out / "val_predictions.csv", setup.val_rec, preds)
    if not args.no_visuals:
        from .visual import log_rerun, plot_paths

        shown = [m for m in ("cc", best_static, best) if m in preds]
        plot_paths(setup, {m: preds[m] for m in dict.fromkeys(shown)}, args.out / "val_tip_paths.png")
        log_rerun(setup, preds, args.out / "val_tip_paths.rrd")
    print(markdown_table(results))
    print(f"best Clarke-space model: {best} (static: {best_static}); wrote {args.out}/results.json ({report['seconds_total']:.0f} s)")
    return report


if __name__ == "__main__":
    main()
