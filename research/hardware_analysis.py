"""Diagnostics behind the benchmark numbers (a frozen research script, formerly ``dacr_learn.hardware.study.analysis``).

Numbers: docs/history/hardware.md, "2026-11-21: Where the error comes from" (hysteresis gap, static floor,
per-family table) and "2026-11-24: Results (FTDCR v4)". It reads FTDCR v4's val.csv (``--val``); never
point it at a hidden hold-out. Run from the repository root:

    python -m research.hardware_analysis --data data/ftdcr_v4 --robot configs/robots/ftdcr_v4_calibrated.yaml

(add ``--run runs/ftdcr_v4``, a benchmark run folder, for the per-family table). It prints

1. the hysteresis gap: within each pattern (a run of equal labels), the rows after the largest
   command are matched to the rows before it with nearly the same command (joint displacements
   within 0.3 mm); the tip distance between such pairs is what no static command → tip map can
   explain (a static model at best sits half way between them);
2. the static floor of the calibrated CC model: the same model fitted on val itself;
3. with ``--run``: the offset-removed RMSE per pattern family (label without its trailing
   digits and "_hold") for every model in RUN/val_predictions.csv.
"""
from __future__ import annotations

import argparse
import csv
import re
import sys
from pathlib import Path

import numpy as np
import torch

from dacr_learn.console import run_cli
from dacr_learn.hardware.calibration import default_map_path
from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.metrics import offset_removed_errors, tip_metrics
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.visual import label_runs
from dacr_learn.robot import RobotSpec


def family(label: str) -> str:
    """Pattern family: the label without a trailing '_hold' and trailing digits.

    Not :func:`dacr_learn.hardware.study.selection.pattern_family`: that one maps train's labels to the
    coarse proxy families (single, pair<jk>) and refuses val's three-segment labels (``all3_same`` …),
    while this table needs a row per pattern kind of val (all3_same, all3_scurve, all3_spiral)."""
    return re.sub(r"\d+$", "", label.removesuffix("_hold"))


def hysteresis_gap(labels, x: torch.Tensor, tip: torch.Tensor, tol: float = 3e-4) -> np.ndarray:
    """Tip distances [m] between unloading rows and the loading row with the nearest command."""
    gaps = []
    for run in label_runs(labels):
        xs, ts = x[run], tip[run]
        peak = int(xs.norm(dim=-1).argmax())
        if peak == 0 or peak == len(xs) - 1:
            continue
        for u in range(peak + 1, len(xs)):
            dist = (xs[:peak + 1] - xs[u]).norm(dim=-1)
            j = int(dist.argmin())
            if dist[j] < tol:
                gaps.append(float((ts[j] - ts[u]).norm()))
    return np.asarray(gaps)


def family_rmse(path: Path) -> dict[str, dict[str, float]]:
    """{model: {family: offset-removed RMSE [mm]}} from a val_predictions.csv (mm)."""
    with open(path) as f:
        rows = list(csv.reader(f))
    header, rows = rows[0], rows[1:]
    labels = [r[0] for r in rows]
    data = np.array([[float(v) for v in r[1:]] for r in rows])
    meas, models = data[:, :3], [h[:-2] for h in header[4::3]]
    out = {}
    fams = sorted(set(map(family, labels)))
    masks = {f: np.array([family(lab) == f for lab in labels]) for f in fams}
    for k, name in enumerate(models):
        # offset removed over the whole file, then the RMSE within each family
        err = offset_removed_errors(torch.from_numpy(data[:, 3 + 3 * k:6 + 3 * k]), torch.from_numpy(meas)).numpy()
        out[name] = {f: float(np.sqrt((err[m] ** 2).mean())) for f, m in masks.items()}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--robot", type=Path, required=True, help="calibrated robot YAML with its servo map")
    ap.add_argument("--train", default="train.csv")
    ap.add_argument("--val", default="val.csv")
    ap.add_argument("--run", type=Path, help="benchmark run folder (reads val_predictions.csv)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    spec = RobotSpec.from_yaml(args.robot)
    smap = ServoMap.from_yaml(default_map_path(args.robot))
    for name in (args.train, args.val):
        rec = load_recording(args.data / name, spec)
        gaps = hysteresis_gap(rec.labels, smap.displacements(spec, rec), rec.tip) * 1e3
        print(f"{name}: hysteresis gap at matched commands over {len(gaps)} pairs: median {np.median(gaps):.2f} mm, "
              f"mean {gaps.mean():.2f} mm, p90 {np.percentile(gaps, 90):.2f} mm")
    val = load_recording(args.data / args.val, spec)
    cc = CalibratedCC(spec)
    x = smap.displacements(spec, val)
    fit_cc(cc, x, val.tip)
    with torch.no_grad():
        print(f"CC model fitted on {args.val} itself (static floor): {tip_metrics(cc(x), val.tip)['rmse_mm']:.2f} mm")
    if args.run:
        table = family_rmse(args.run / "val_predictions.csv")
        fams = list(next(iter(table.values())))
        print("| model | " + " | ".join(fams) + " |\n|---|" + "---|" * len(fams))
        for name, row in table.items():
            print(f"| `{name}` | " + " | ".join(f"{row[f]:.2f}" for f in fams) + " |")


if __name__ == "__main__":
    sys.exit(run_cli(main))
