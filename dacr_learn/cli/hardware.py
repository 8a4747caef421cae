"""``python -m dacr_learn.hardware --data DIR --robot YAML --out runs/NAME``

Calibrates (when the robot YAML has no servo map), fits the CC model, scores every tip model
with the train-only selection proxies and chooses the default model, trains all models on
``DIR/<train>`` and, when ``DIR/<val>`` exists, evaluates them on it. Writes into ``--out``:
results.json (proxies, ``default_model``, val metrics), results.md (table) and, with a
validation recording, val_predictions.csv (first seed, mm), val_tip_paths.png and
val_tip_paths.rrd (Rerun).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

from ..hardware.study import benchmark, heldout
from ..hardware.study.benchmark import SelectionResult, Setup
from ..hardware.study.pool import TaskPool
from ..hardware.study.registry import MODELS, model_info
from ..hardware.study.selection import CC_VARIANTS, DEFAULT_PROXIES, PROXIES, SELECTION_PROXY, default_choice
from ..hardware.study.table import markdown_table


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m dacr_learn.hardware", description=__doc__.split("\n\n")[1])
    ap.add_argument("--data", type=Path, required=True, help="folder with the recordings")
    ap.add_argument("--robot", type=Path, required=True,
                    help="robot YAML (with servo_maps/<name> next to it, or nominal)")
    ap.add_argument("--out", type=Path, required=True, help="run folder to write")
    ap.add_argument("--train", default="train.csv", help="training recording, relative to --data")
    ap.add_argument("--val", default="val.csv", help="validation recording, relative to --data (optional: "
                    "without it the models are scored with the train-only proxies alone)")
    ap.add_argument("--pulls", default="tendon_pull.csv",
                    help="single-pull recording for calibration when the robot has no servo map")
    ap.add_argument("--servo-map", type=Path,
                    help="servo map YAML (default: servo_maps/<robot file name> next to the robot)")
    ap.add_argument("--units", default="mm", choices=["mm", "m"])
    ap.add_argument("--cc-variant", default="auto", choices=["auto", *CC_VARIANTS],
                    help="calibrated CC model variant (base: one pretension; strain: pretension ∝ tendon path "
                         "length, +1 parameter); auto (default): the lower singles→pairs score of the CC model")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of the final training runs")
    ap.add_argument("--proxy-seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="seeds of the selection proxies of the default candidates (the other models, scored for "
                         "comparison, use the first); the proxies' uncertainty bootstraps over them and over the "
                         "held-out pattern groups")
    ap.add_argument("--no-proxies", action="store_true",
                    help="skip the selection proxies (no default model; needs pattern labels otherwise)")
    ap.add_argument("--proxies", nargs="+", default=list(DEFAULT_PROXIES), choices=PROXIES,
                    help=f"selection proxies to compute (default: {SELECTION_PROXY}, which chooses the default "
                    "model; add cv for the family cross-validation column, 4 more fits per model and seed)")
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads per process (1 is fastest for these sizes)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="worker processes for the fits (default: 2, or 1 on a one-core machine; 1: in this process)")
    ap.add_argument("--no-visuals", action="store_true", help="skip the PNG and the Rerun recording")
    ap.add_argument("--save", type=Path, help="write the default model (one member per --seeds) as DIR/model.pt "
                    "(load_hardware_model; export with python -m dacr_learn.export --ckpt DIR/model.pt)")
    args = ap.parse_args(argv)
    if SELECTION_PROXY not in args.proxies:
        ap.error(f"--proxies must include {SELECTION_PROXY} (the default model is chosen on it), got {args.proxies}")
    if args.jobs < 1 or args.threads < 1:
        ap.error(f"--jobs and --threads: expected >= 1, got {args.jobs} and {args.threads}")
    return args


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
    """The candidate with the lowest mean val RMSE, or None (also without val)."""
    names = [k for k in results if k in candidates and "val" in results[k]]
    return min(names, key=lambda k: results[k]["val"]["rmse_mm"]["mean"]) if names else None


def _val_path(args: argparse.Namespace) -> Path | None:
    """``--data``/``--val`` when it exists, else None (reported by :func:`run` once the inputs have loaded)."""
    path = args.data / args.val
    return path if path.exists() else None


def _selection_folds(setup: Setup, args: argparse.Namespace) -> dict:
    """{proxy: folds}, or {} (with the reason printed) without proxies or when the labels name no families."""
    if args.no_proxies:
        return {}
    try:
        return benchmark.selection_folds(setup, args.proxies)
    except ValueError as err:
        print(f"no selection proxies, so no default model: {err}")
        return {}


def _fit_all(setup: Setup, args: argparse.Namespace, start: float
             ) -> tuple[SelectionResult | None, dict | None, dict, dict, dict]:
    """(proxies or None, the default's choice or None, final results, val predictions, what ``--save`` needs):
    every fit handed to one pool before any is collected. With ``--save`` the saved ensemble is the final runs'
    members, and the σ model's held-out rows are the default's proxy fits when its proxy seeds are ``--seeds``:
    {"members": {model: models per seed}, "held_out": [HeldOut]} (empty without ``--save``).
    """
    keep = benchmark.default_candidates(list(args.models)) if args.save else ()
    fitted: dict = {}
    models = tuple(args.models)
    folds = _selection_folds(setup, args)
    proxy_seeds = benchmark.proxy_seeds_of(models, args.proxy_seeds, benchmark.default_candidates(list(models)))
    with TaskPool(args.jobs, args.threads) as pool:
        fits = [(f.ctx, m, proxy_seeds[m]) for fs in folds.values() for f in fs for m in models]
        warm = benchmark.submit_warmups(pool, fits + [(setup.context(), m, args.seeds) for m in models],
                                        benchmark.progress, start)
        pending = (benchmark.submit_selection(pool, setup, models, args.proxy_seeds, args.proxies,
                                              benchmark.default_candidates(list(models)), folds) if folds else None)
        final = benchmark.submit_benchmark(pool, setup, models, tuple(args.seeds), keep)
        proxy_fits = 0 if pending is None else sum(len(fs) for per in pending.fits.values()
                                                   for folds in per.values() for fs in folds.values())
        benchmark.progress(f"[start] {len(models)} models on {args.jobs} worker(s): {len(warm)} shared Cosserat "
                           f"piece(s), {proxy_fits} proxy fits, {sum(len(fs) for fs in final.values())} final runs; a "
                           f"line per model as its proxies ([proxy k/{len(models)}]) and its final runs ([final "
                           f"k/{len(models)}]) finish")
        selection = benchmark.collect_selection(pending, start=start) if pending is not None else None
        choice = None
        if selection is not None and benchmark.default_candidates(list(selection.scores)):
            choice = benchmark.select_default(selection.scores, selection.replicates)
        default = choice["default"] if choice else None
        blocks = heldout.held_out_from_selection(selection, default, args.seeds) if keep and default else None
        sigma = (heldout.submit_held_out(pool, setup, default, args.seeds, heldout.SIGMA_PROXIES)
                 if keep and default and not blocks else [])
        results, preds = benchmark.collect_benchmark(final, tuple(args.seeds), fitted=fitted, start=start)
        saving = {"members": fitted, "held_out": blocks or heldout.collect_held_out(sigma)} if keep else {}
        for f in warm:                              # surfaces a failed shared piece (its fits computed it again)
            f.result()
    return selection, choice, results, preds, saving


def run(args: argparse.Namespace, argv: list[str] | None = None) -> tuple[dict, Setup, dict]:
    """The benchmark of ``args``; returns (the results.json report, the setup, what ``--save`` needs: the
    fitted default candidates and the σ model's held-out folds, :func:`_fit_all`; {} without ``--save``).
    The default model is ``report["default_model"]``."""
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    setup = benchmark.load_setup(args.robot, args.data / args.train, _val_path(args), args.out,
                                 args.servo_map, args.data / args.pulls, args.units, args.cc_variant)
    with tempfile.TemporaryDirectory(prefix="dacr_hardware_") as cache:
        setup.cache_dir = Path(cache)                # the workers share the Cosserat calibrations here
        try:
            return _run(args, argv, setup, start)
        finally:
            setup.cache_dir = None


def _run(args: argparse.Namespace, argv: list[str] | None, setup: Setup, start: float) -> tuple[dict, Setup, dict]:
    if setup.val_rec is None:     # printed after loading: an error in the robot or train file comes first
        print(f"no validation recording {args.data / args.val}: scoring with the train-only selection proxies only")
    variant = setup.cc_fit["variant"]
    if "extrap" in variant:
        print(f"CC variant {variant['chosen']!r}, chosen by the CC model's singles→pairs score "
              f"({', '.join(f'{k} {v:.2f} mm' for k, v in variant['extrap'].items())})")
    print(f"CC fit on {len(setup.train_rec)} rows: {setup.cc_fit['rms_m'] * 1e3:.2f} mm rms "
          f"({setup.cc_fit['seconds']:.1f} s); parameters {setup.cc_fit['parameters']}")
    selection, choice, results, preds, saving = _fit_all(setup, args, start)
    scores = selection.scores if selection is not None else {}
    chosen = choice or {}
    default = chosen.get("default")
    everyone = benchmark.default_candidates(list(scores), deployable_only=False)
    reps = {m: r[SELECTION_PROXY] for m, r in selection.replicates.items()} if selection is not None else None
    proxy_best = default_choice(scores, everyone, SELECTION_PROXY, reps)["default"] if everyone else None
    if proxy_best is not None and not model_info(proxy_best).deployable:
        print(f"note: among all Clarke-space models the rule would choose {proxy_best}, but --save and the export "
              f"do not support it yet; the default is chosen among the deployable ones, {default}")
    clarke = tuple(m for m in results if model_info(m).clarke_space)
    report = {"command": "python -m dacr_learn.hardware " + " ".join(sys.argv[1:] if argv is None else argv),
              "robot": setup.spec.to_dict(), "train": str(args.data / args.train),
              "val": str(setup.val_rec.source) if setup.val_rec is not None else None,
              "rows": {"train": len(setup.train_rec), "val": len(setup.val_rec) if setup.val_rec is not None else 0},
              "calibration": setup.calibration, "cc_fit": setup.cc_fit,
              "default_model": default,
              "selection": {"proxy": SELECTION_PROXY, "candidates": list(benchmark.default_candidates(list(scores))),
                            "rule": chosen.get("rule"), "reason": chosen.get("reason"),
                            "best_by_proxy": chosen.get("best"), "tied": chosen.get("tied", []),
                            "comparison": chosen.get("candidates", {}),
                            "best_clarke_model_by_proxy": proxy_best,
                            "proxy_seeds": args.proxy_seeds, "proxies": [] if not scores else args.proxies,
                            "scores": scores},
              "models": results, "best_clarke_model": best_model(results, clarke),
              "best_static_clarke_model": best_model(results, tuple(m for m in clarke if model_info(m).static)),
              "environment": {"torch": torch.__version__, "threads": args.threads, "jobs": args.jobs,
                              "python": platform.python_version()}}
    report["seconds_total"] = time.perf_counter() - start
    (args.out / "results.json").write_text(json.dumps(report, indent=1))
    (args.out / "results.md").write_text(markdown_table(results, scores, default) + "\n")
    if preds:
        write_predictions(args.out / "val_predictions.csv", setup.val_rec, preds)
    if preds and not args.no_visuals:
        from ..hardware.study.visual import log_rerun, plot_paths

        # the CC model, the best static Clarke model and the default (without proxies: the best Clarke model)
        third = default or report["best_clarke_model"]
        shown = [m for m in ("cc", report["best_static_clarke_model"], third) if m in preds]
        plot_paths(setup, {m: preds[m] for m in dict.fromkeys(shown)}, args.out / "val_tip_paths.png")
        log_rerun(setup, preds, args.out / "val_tip_paths.rrd", default=default)
    print(markdown_table(results, scores, default))
    if choice:
        print(f"default model (train only): {default} — {choice['reason']}")
    print(f"best on val: {report['best_clarke_model']}; wrote {args.out}/results.json "
          f"({report['seconds_total']:.0f} s)")
    return report, setup, saving


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    report, setup, saving = run(args, argv)
    if args.save and report["default_model"] is not None:
        from ..hardware.deploy.checkpoint import save_hardware_model, support_warning

        model = benchmark.fit_hardware_model(setup, report["default_model"], args.seeds,
                                             info={"command": report["command"]},
                                             members=saving["members"].get(report["default_model"]))
        model.sigma, model.sigma_model = heldout.sigma_models_of(saving["held_out"])
        path = save_hardware_model(model, args.save / "model.pt")
        print(f"saved the default model {report['default_model']} ({len(model.members)} members, σ model "
              f"{model.sigma_model.describe()} fitted on held-out train rows) to {path}")
        warning = support_warning(model, setup.val) if setup.val is not None else None
        if warning:
            print(warning)
    return report

