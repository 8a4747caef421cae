"""Extra physical parameters of the static calibrated CC model (research script).

Two physical freedoms the calibrated CC model lacks, both identifiable from train (pairs and the
distal tendon pulls bend several segments at once):
- ``pass``: the moment arm of a tendon that only passes a segment (it drives a more distal one)
  differs from that of the segment's own tendons by a factor exp(a_k) (one per passed segment, or
  one shared: ``pass1``); the displacement map G and the force balance use it alike.
- ``stiff``: per-segment bending stiffness, EI_k = EI·exp(s_k) with s_0 = 0 (m − 1 parameters).
- ``marker3``: the marker offset as a 3-vector in the tip frame (2 more parameters than the axial
  offset; since promoted to the package model: ``CalibratedCC(spec, lateral_marker=True)``, which
  this variant now uses; ``base`` is ``lateral_marker=False``).
Static CC only (no residual network). Reports in-sample train RMSE, leave-one-family-out CV RMSE,
the singles → pairs extrapolation RMSE (fit on the single-segment family, test on all pairs), the
radial bias of loading rows by family (positive = over-bends) and the marker offset [mm] fitted in
each fold (--val: also FTDCR v4's val.csv; never with HW_ROBOT=v6). ~6 s per variant.

Numbers: docs/history/hardware.md, "2026-11-21: Third round: static physics and a better selection
proxy" (the static rows), "2026-11-23: FTDCR v6, the second robot" (HW_ROBOT=v6,
results/static_variants_v6.jsonl) and "2026-11-23: Lateral marker offset" (`marker3`, key `marker_mm`).
Run from the repository root: [HW_ROBOT=v6] python -m research.hardware_cv.static_variants VARIANT[,VARIANT...] [--val]
  VARIANT: base | pass1 | pass | stiff | marker3, or several joined by '+'
e.g.   HW_ROBOT=v6 python -m research.hardware_cv.static_variants base,stiff,pass1,marker3
"""

import argparse
import json
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.slack import SlackAwareEncoder

from .common import FOLDS, rmse, setup, val_data

SCALES = {"encoder.pass_log_scale": 0.1, "encoder.log_stiffness": 0.1}  # extra fit_cc scales


class CoupledEncoder(SlackAwareEncoder):
    def __init__(self, spec, variant: str):
        super().__init__(spec, compliance=1e-6)
        self.variant = variant
        m = spec.num_segments
        owner = self.segment_of_joint
        self.register_buffer("passing", (torch.arange(m)[None, :] < owner[:, None]).double())  # (N, m)
        n_pass = 1 if "pass1" in variant else m
        self.pass_log_scale = nn.Parameter(torch.zeros(n_pass, dtype=torch.float64))
        self.log_stiffness = nn.Parameter(torch.zeros(m - 1, dtype=torch.float64))

    def displacement_map(self):
        g = super().displacement_map()
        if "pass" not in self.variant:
            return g
        scale = self.pass_log_scale.expand(self.spec.num_segments).exp()  # (m,)
        factor = 1 + self.passing * (scale - 1)  # (N, m)
        return g * factor.repeat_interleave(2, dim=-1)

    def bend_weights(self):
        if "stiff" not in self.variant:
            return super().bend_weights()
        stiff = torch.cat([torch.zeros(1, dtype=torch.float64), self.log_stiffness]).exp()
        return super().bend_weights() * stiff.repeat_interleave(2)


class VariantCC(CalibratedCC):
    def __init__(self, spec, variant: str):
        super().__init__(spec, lateral_marker="marker3" in variant)
        self.variant = variant
        self.encoder = CoupledEncoder(spec, variant)


def marker_mm(cc) -> list[float]:
    """Fitted marker offset (x, y, t) [mm] in the tip frame."""
    return [round(v * 1e3, 2) for v in cc.marker_offset().tolist()]


def make(variant):
    return VariantCC(setup().spec, variant)


def fitted(variant, x, tip):
    cc = make(variant)
    fit_cc(cc, x, tip, scales=SCALES)
    return cc


def kinds_of(labels) -> np.ndarray:
    """Row kinds of train: pull, single, same, opp."""
    return np.array(
        ["pull" if "tendon" in s else "single" if "_seg" in s else ("same" if "same" in s else "opp") for s in labels]
    )


def loading_bias(cc, x, tip, kinds):
    with torch.no_grad():
        pred, straight = cc(x), cc(torch.zeros(1, x.shape[1]))[0]
        th = (cc.encoder.clarke(x).norm(dim=-1) / cc.encoder.effective_radius()).sum(-1)
    r = ((pred[:, :2] - straight[:2]).norm(dim=-1) - (tip[:, :2] - straight[:2]).norm(dim=-1)) * 1e3
    load = torch.cat([torch.zeros(1, dtype=torch.bool), th[1:] > th[:-1] + 1e-4])
    return {k: round(r[load & torch.from_numpy(kinds == k)].mean().item(), 2) for k in sorted(set(kinds))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("variants")
    ap.add_argument("--val", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    kind = kinds_of(d.train_rec.labels)
    for v in a.variants.split(","):
        t0 = time.time()
        cc = fitted(v, x_tr, tip_tr)
        out = {"name": v, "train": round(rmse(cc(x_tr).detach(), tip_tr), 3)}
        folds, markers = {}, {"train": marker_mm(cc)}
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            fold_cc = fitted(v, x_tr[tr], tip_tr[tr])
            folds[f], markers[f] = rmse(fold_cc(x_tr[~tr]).detach(), tip_tr[~tr]), marker_mm(fold_cc)
        single = torch.from_numpy(fam == "single")
        single_cc = fitted(v, x_tr[single], tip_tr[single])
        extrap, markers["singles"] = rmse(single_cc(x_tr[~single]).detach(), tip_tr[~single]), marker_mm(single_cc)
        out.update(
            cv=round(float(np.mean(list(folds.values()))), 3),
            singles_to_pairs=round(extrap, 3),
            folds={k: round(s, 2) for k, s in folds.items()},
            load_bias_train=loading_bias(cc, x_tr, tip_tr, kind),
            marker_mm=markers,
            params={
                n: [round(t, 4) for t in p.detach().flatten().tolist()]
                for n, p in cc.named_parameters()
                if "pass" in n or "stiff" in n or "marker" in n or "tip_offset" in n
            },
        )
        if a.val:
            x_va, tip_va = val_data()
            out["VAL"] = round(rmse(cc(x_va).detach(), tip_va), 3)
        out["s"] = round(time.time() - t0, 1)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
