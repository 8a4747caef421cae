"""σ models of the default hardware model (g) on ftdcr_v4: chosen on held-out train folds, reported on val.

Numbers: docs/history/hardware.md, "2026-11-23: Uncertainty: σ per prediction and out-of-support score"
(the table of 13 σ models and the v4 val report). Run from the repository root:

    python -m research.hardware_cv.ensemble_uncertainty --members 4 --out /tmp/unc.pt   # ~30 min loaded
    python -m research.hardware_cv.ensemble_uncertainty --load /tmp/unc.pt               # analysis only, 20 s

1. Collect (``--out``): for every fold of :func:`dacr_learn.hardware.study.selection.proxy_masks` (family
   CV: single, pair12, pair13, pair23; extrap: singles → pairs) the CC model is refitted on the
   fold's training rows, K members of (g) (seeds 0..K−1) are trained there, and on the held-out
   rows the members' tips, the CC tip, the measured tip, ρ and the support distance (to the fold's
   training rows) are kept. The same on all of train.csv → val.csv (the val block is only read at
   the very end of the analysis, for the report).
2. Analyse: each σ model of :data:`CANDIDATES` (terms of :class:`~dacr_learn.hardware.deploy.uncertainty.SigmaModel`)
   is fitted by Gaussian likelihood on held-out train residuals and scored, still on train, by
   (a) leave-one-CV-fold-out (fit on three families, score the fourth) and (b) fit on the four CV
   folds, score the singles → pairs fold. Scores: ±2σ coverage per axis and Spearman(‖σ‖, ‖e − ē‖),
   ē the mean error of the scored rows. The design is chosen on (b) (the shift most like val's), then
   fitted on all five folds and reported once on v4 val.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from dacr_learn.hardware.deploy.uncertainty import coverage, spearman
from dacr_learn.hardware.study.benchmark import load_setup
from dacr_learn.hardware.study.heldout import HeldOut, fit_sigma_model, held_out, held_out_folds

from .common import ROOT

DATA = ROOT / "data" / "ftdcr_v4"
ROBOT = ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"
MODEL = "cc_clarke_residual_history"
EXTRAP = "extrap:singles_to_pairs"
CANDIDATES = {          # name → SigmaModel terms (see uncertainty.TERMS)
    "ensemble (s, σ₀)": ("ensemble",),
    "CC disagreement": ("disagreement",),
    "support distance": ("support",),
    "bend ‖ρ‖": ("bend",),
    "ensemble + support": ("ensemble", "support"),
    "ensemble + bend": ("ensemble", "bend"),
    "ensemble + disagreement": ("ensemble", "disagreement"),
    "disagreement + bend": ("disagreement", "bend"),
    "disagreement + support": ("disagreement", "support"),
    "ensemble + support + bend": ("ensemble", "support", "bend"),
    "ensemble + disagreement + bend": ("ensemble", "disagreement", "bend"),
    "ensemble + disagreement + support": ("ensemble", "disagreement", "support"),
    "all four": ("ensemble", "disagreement", "support", "bend"),
}


def collect(k: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:    # only written to when calibrating from pulls, never here
        setup = load_setup(ROBOT, DATA / "train.csv", DATA / "val.csv", Path(tmp))
    start = time.perf_counter()
    log = lambda msg: print(f"{msg} ({time.perf_counter() - start:.0f} s)", flush=True)  # noqa: E731
    blocks = held_out_folds(setup, MODEL, range(k), log=log)
    val = held_out(MODEL, setup.context(), setup.val, setup.train_rec.labels, range(k), "val")
    return {"k": k, "folds": {b.fold: b.to_dict() for b in blocks}, "val": val.to_dict()}


def score(model, block: HeldOut) -> tuple[float, float, float]:
    """(±2σ coverage, Spearman(‖σ‖, ‖e − ē‖), median ‖σ‖ [mm]) of a fitted σ model on one block."""
    sigma, residual = model(block.features()), block.residual()
    return coverage(residual, sigma), spearman(sigma.norm(dim=-1), residual.norm(dim=-1)), \
        float(sigma.norm(dim=-1).median()) * 1e3


def candidate_scores(terms, folds: dict[str, HeldOut]) -> tuple[float, float, tuple]:
    """Leave-one-CV-fold-out (mean coverage, mean Spearman) and (b): fit on the CV folds, score singles → pairs."""
    cv = [k for k in folds if k.startswith("cv:")]
    loo = [score(fit_sigma_model([folds[o] for o in cv if o != f], terms), folds[f]) for f in cv]
    ext = score(fit_sigma_model([folds[f] for f in cv], terms), folds[EXTRAP])
    return sum(s[0] for s in loo) / len(loo), sum(s[1] for s in loo) / len(loo), ext


def analyse(res: dict) -> str:
    folds = {name: HeldOut(**{**d, "fold": name}) for name, d in res["folds"].items()}
    rows, best = [], None
    for name, terms in CANDIDATES.items():
        cov_loo, rho_loo, ext = candidate_scores(terms, folds)
        rows.append(f"| {name} | {cov_loo * 100:.1f} | {rho_loo:+.2f} | {ext[0] * 100:.1f} | {ext[1]:+.2f} | "
                    f"{ext[2]:.2f} |")
        key = (0.85 <= ext[0] <= 0.99, ext[1])
        if best is None or key > best[0]:
            best = (key, name)
    chosen = best[1]
    final = fit_sigma_model(list(folds.values()), CANDIDATES[chosen])
    val_block = HeldOut(**{**res["val"], "fold": "val"})
    val = score(final, val_block)
    raw = score(fit_sigma_model(list(folds.values()), ("ensemble",)), val_block)
    saved = fit_sigma_model([folds[EXTRAP]], CANDIDATES[chosen])          # what --save fits (heldout.sigma_models)
    on_cv = [score(saved, b) for name, b in folds.items() if name != EXTRAP]
    saved_val = score(saved, val_block)
    return "\n".join([
        f"K = {res['k']} members of {MODEL}; σ models fitted by Gaussian likelihood on held-out train folds",
        "| σ model | CV-fold coverage [%] | CV-fold Spearman | singles→pairs coverage [%] | "
        "singles→pairs Spearman | median ‖σ‖ [mm] |", "|---|---|---|---|---|---|", *rows, "",
        f"chosen on singles→pairs (coverage in 85–99 %, then the highest Spearman): {chosen}",
        f"fitted on all five train folds: {final.describe()}",
        f"v4 val (report only): ±2σ coverage {val[0] * 100:.1f} %, Spearman {val[1]:+.3f}, median ‖σ‖ "
        f"{val[2]:.2f} mm   (ensemble-only σ fitted the same way: {raw[0] * 100:.1f} %, {raw[1]:+.3f})",
        f"fitted on singles→pairs alone (as --save): {saved.describe()}; on the CV folds "
        f"{sum(c for c, _, _ in on_cv) / len(on_cv) * 100:.1f} %, {sum(r for _, r, _ in on_cv) / len(on_cv):+.2f}; "
        f"v4 val {saved_val[0] * 100:.1f} %, {saved_val[1]:+.3f}"])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--members", type=int, default=4)
    ap.add_argument("--out", default="/tmp/ensemble_uncertainty.pt")
    ap.add_argument("--load", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    res = torch.load(args.load, weights_only=True) if args.load else collect(args.members)
    if not args.load:
        torch.save(res, args.out)
    print(analyse(res))


if __name__ == "__main__":
    main()
