"""Radial bias of the tip while loading / unloading, binned by the total bend (research script).

Radial error = |predicted tip − straight tip|_xy − |measured tip − straight tip|_xy [mm]
(positive: the model over-bends). Rows count as loading when the summed bend of the static CC
encoder grows. Families: single segments, tendon pulls (of segments 1–2 / of the distal segment 3, which bend all
three segments), pairs bending the same / opposite way.
- static CC fitted on all of train (in-sample), and on single segments only (tested on pairs);
- model (g) fitted on single segments only (2 seeds, prediction averaged), tested on pairs;
- with --val: the static CC fitted on train, on val's all3_same / scurve / spiral (a diagnosis
  after the fact; used for no choice). 25 s.

Numbers: docs/history/hardware.md, "2026-11-21: Third round: static physics and a better selection
proxy" (radial bias while loading; output in results/loading_bias.txt).
Run from the repository root: python -m research.hardware_cv.loading_bias [--val]
"""

import argparse
import re

import numpy as np
import torch

from dacr_learn.hardware.recording import load_recording

from .common import bend_angles, fit, setup, val_data
from .residual_memory import fit_predict

BINS = [(0, 0.5), (0.5, 1), (1, 1.5), (1.5, 2), (2, 3)]


def kinds_of(labels) -> np.ndarray:
    """Row kinds of train: pull_distal (tendons 6-8: segment 3), pull, single, same, opp."""
    return np.array(
        [
            "pull_distal"
            if re.search(r"tendon[678]_", s)
            else "pull"
            if "tendon" in s
            else "single"
            if "_seg" in s
            else ("same" if "same" in s else "opp")
            for s in labels
        ]
    )


def table(title, cc, x, tip, kinds, pred):
    with torch.no_grad():
        straight = cc(torch.zeros(1, x.shape[1]))[0]
    r = ((pred[:, :2] - straight[:2]).norm(dim=-1) - (tip[:, :2] - straight[:2]).norm(dim=-1)) * 1e3
    th = bend_angles(cc, x).sum(-1)
    dt = torch.cat([torch.zeros(1, dtype=th.dtype), th[1:] - th[:-1]])
    print(
        f"{title}  (bins of total bend: "
        + ", ".join(f"{a}-{b}" for a, b in BINS)
        + " rad; mean radial error mm (rows))"
    )
    for k in sorted(set(kinds)):
        mk = torch.from_numpy(kinds == k)
        for name, dm in (("load", dt > 1e-4), ("unload", dt < -1e-4)):
            cells = []
            for lo, hi in BINS:
                s = mk & dm & (th >= lo) & (th < hi)
                cells.append(f"{r[s].mean().item():5.1f} ({int(s.sum()):3d})" if s.sum() > 3 else "     -     ")
            print(f"  {k:11s} {name:6s} " + "  ".join(cells))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--val", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    train_kind = kinds_of(d.train_rec.labels)
    cc = fit(x_tr, tip_tr)
    with torch.no_grad():
        table("static CC fitted on train, in-sample", cc, x_tr, tip_tr, train_kind, cc(x_tr))
    single = torch.from_numpy(fam == "single")
    pairs = ~single
    cc1 = fit(x_tr[single], tip_tr[single])
    with torch.no_grad():
        table(
            "static CC fitted on single segments, on the pairs",
            cc1,
            x_tr[pairs],
            tip_tr[pairs],
            train_kind[~single.numpy()],
            cc1(x_tr[pairs]),
        )
    cfg = {"width": 1e-4, "mem_in": True, "lin": [], "c0": False}
    preds = [fit_predict(cfg, cc1, x_tr, tip_tr, single, pairs, seed)[1] for seed in (0, 1)]
    table(
        "(g) fitted on single segments (2 seeds averaged), on the pairs",
        cc1,
        x_tr[pairs],
        tip_tr[pairs],
        train_kind[~single.numpy()],
        torch.stack(preds).mean(0),
    )
    if a.val:
        x_va, tip_va = val_data()
        labels = load_recording(d.data / "val.csv", d.spec).labels
        kinds = np.array(["all3_same" if "same" in s else "scurve" if "scurve" in s else "spiral" for s in labels])
        with torch.no_grad():
            table("VAL (diagnosis only): static CC fitted on train", cc, x_va, tip_va, kinds, cc(x_va))


if __name__ == "__main__":
    main()
