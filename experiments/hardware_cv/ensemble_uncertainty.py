"""Deep-ensemble σ of model (g) on ftdcr_v4: calibration by family CV on train, report on val.

    .venv/bin/python experiments/hardware_cv/ensemble_uncertainty.py --members 4 --out /tmp/unc.pt
    .venv/bin/python experiments/hardware_cv/ensemble_uncertainty.py --load /tmp/unc.pt   # report only

1. Family CV on train.csv (folds of common.FOLDS): per fold the CC model is refitted on the other
   families, K members of ``cc_clarke_residual_history`` (seeds 0..K−1) are trained, and their mean,
   std and the offset-removed residuals on the held-out family are kept.
2. :class:`SigmaCalibration` is fitted to those held-out residuals (train only).
3. The same K members trained on all of train.csv predict val.csv (evaluation only, never used to
   choose anything): coverage of ±2σ per axis and Spearman(‖σ‖, ‖e − ē‖), raw and calibrated, and
   the out-of-support score of the val commands.
"""
from __future__ import annotations

import argparse
import time

import torch
from common import FOLDS, fam, smap, spec, train_rec

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.learned import CCClarkeResidualHistory, make_split
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.uncertainty import SigmaCalibration, SupportModel, ensemble_predict


def members_on(train_rec_, test_rec, k: int):
    """Refit CC on train_rec_, train k members; (mean, std, tip) on test_rec and the train split."""
    cc = CalibratedCC(spec)
    fit_cc(cc, smap.displacements(spec, train_rec_), train_rec_.tip)
    for p in cc.parameters():
        p.requires_grad_(False)
    tr, te = make_split(train_rec_, spec, smap, cc), make_split(test_rec, spec, smap, cc)
    models = []
    for seed in range(k):
        torch.manual_seed(seed)
        m = CCClarkeResidualHistory(tr, cc)
        m.fit(tr)
        models.append(m)
    mean, std = ensemble_predict(models, te)
    return mean, std, te.tip, tr, te


def offset_removed(mean, tip):
    e = mean - tip
    return e - e.mean(0)


def spearman(a, b) -> float:
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def report(name, res, std):
    cover = float(((res.abs() <= 2 * std).double()).mean())
    rho = spearman(std.norm(dim=-1), res.norm(dim=-1))
    rmse = float(res.pow(2).sum(-1).mean().sqrt()) * 1e3
    print(f"{name:34s} ±2σ coverage {cover * 100:5.1f} %   Spearman(‖σ‖, ‖e‖) {rho:+.3f}   "
          f"median ‖σ‖ {float(std.norm(dim=-1).median()) * 1e3:.2f} mm  rmse {rmse:.2f} mm")
    return cover, rho


def run(k: int) -> dict:
    out = {"cv": [], "k": k}
    for fold in FOLDS:
        t0 = time.perf_counter()
        held = torch.as_tensor(fam == fold)
        mean, std, tip, _, te = members_on(train_rec.select(~held), train_rec.select(held), k)
        out["cv"].append({"fold": fold, "residual": offset_removed(mean, tip), "std": std})
        print(f"fold {fold}: {time.perf_counter() - t0:.0f} s", flush=True)
    val_rec = load_recording(common_val_path(), spec)
    mean, std, tip, tr, te = members_on(train_rec, val_rec, k)
    out.update(val_residual=offset_removed(mean, tip), val_std=std, train_rho=tr.features[..., :2],
               val_rho=te.features[..., :2])
    return out


def common_val_path():
    import common
    return common.DATA / "val.csv"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--members", type=int, default=4)
    ap.add_argument("--out", default="/tmp/ensemble_uncertainty.pt")
    ap.add_argument("--load", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    res = torch.load(args.load, weights_only=False) if args.load else run(args.members)
    if not args.load:
        torch.save(res, args.out)
    cv_res = torch.cat([f["residual"] for f in res["cv"]])
    cv_std = torch.cat([f["std"] for f in res["cv"]])
    cal = SigmaCalibration.fit(cv_res, cv_std)
    print(f"K = {res['k']}; calibration on train family CV: scale {float(cal.scale):.2f}, "
          f"floor {float(cal.floor) * 1e3:.2f} mm")
    report("train family CV, raw σ", cv_res, cv_std)
    report("train family CV, calibrated σ", cv_res, cal(cv_std))
    report("v4 val, raw ensemble σ", res["val_residual"], res["val_std"])
    report("v4 val, calibrated σ (train CV)", res["val_residual"], cal(res["val_std"]))
    support = SupportModel(res["train_rho"], list(train_rec.labels))
    score = support(res["val_rho"])
    err = res["val_residual"].norm(dim=-1)
    print(f"v4 val out-of-support: {float((score > 1).double().mean()) * 100:.1f} % of rows score > 1, "
          f"{float(support.outside_box(res['val_rho']).double().mean()) * 100:.1f} % outside the training box; "
          f"Spearman(score, ‖e‖) {spearman(score, err):+.3f}; error of flagged rows "
          f"{float(err[score > 1].mean()) * 1e3 if bool((score > 1).any()) else float('nan'):.2f} mm vs "
          f"{float(err[score <= 1].mean()) * 1e3:.2f} mm")


if __name__ == "__main__":
    main()
