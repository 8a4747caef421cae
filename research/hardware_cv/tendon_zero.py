"""Why the calibrated CC model fits FTDCR v6 badly: tendon zero offsets and pretension (issue 12).

The package CC model shares one pretension p across all tendons: tendon i is taut when
x_i + p > (Gρ)_i. If the tendons were tied off at different lengths, each has its own taut point
(the "taut onset" the calibration reports per servo: v4 −0.13 … −1.51 mm, v6 −0.55 … −4.23 mm).
Candidates (static, physically motivated, few parameters), all on top of the package model
(``CalibratedCC``, lateral marker):

- ``base``: the package model;
- ``zero``: per-tendon zero offsets δ (N fitted, zero mean: the common part is the pretension),
  x_i → x_i + δ_i; ``zero_r<σ>``: with a Gaussian prior δ ~ N(0, σ mm) (MAP, tip noise 5 mm);
- ``zero_seg``: the zero offsets only as a mean per segment (m fitted, zero mean over joints);
- ``strain``: pretension stretch grows with the path length, p_i = p + s·(L_i − L̄)/L̄ (+1 parameter:
  a common pretension *force* stretches each tendon ∝ its length; s = p is pure strain);
- ``zero_cal``: δ_i = −(taut onset_i − mean onset) fixed from the calibration's pull line fits (+0);
- ``gain``: per-tendon displacement gain x_i → x_i·exp(g_i) (N fitted: spool radius / stretch);
  ``zero+gain``: both;
- ``pullzero``: per-tendon offsets active only in the pull regime (all other tendons parked below
  half the slack level) — nuisance parameters that let the pulls inform the rest without their
  taut points; ``strain+pullzero``: both;
- ``series[+strain]``: tendon stiffness 1/(L_i + L0), a series compliance at the actuator (+1);
- ``axial[R0][+strain]``: backbone axial compression as m extra coordinates in the tendon QP
  (r = EA_backbone/EA_tendon fitted, start R0): many taut tendons shorten the backbone.

Selection rule, fixed before scoring (brief of issue 12): a candidate counts only if, on both
FTDCR v4 and v6, neither proxy (family CV, singles → pairs) is worse than ``base`` by more than
0.10 mm ("neutral"), and on at least one robot both proxies are ≥ 0.20 mm better ("clearly better").

Numbers: docs/history/hardware.md, "2026-11-23: Fourth round: pretension that grows with the tendon
length, chosen per robot" (results/tendon_zero.jsonl, results/tendon_zero_subsets.jsonl).
Run from the repository root:

    python -m research.hardware_cv.tendon_zero ROBOT VARIANTS [--diag | --subsets | --no-pull-test]

→ one JSON line per variant (train, cv, extrap [mm], per fold, fitted offsets) appended to
results/tendon_zero.jsonl; --diag prints per-label RMSE of the fits on all train; --subsets fits
on parts of train (pulls, single-segment patterns, pair12, …) → results/tendon_zero_subsets.jsonl;
--no-pull-test drops the pull rows from every test set (information only, not a selection proxy).
About 10 s per variant and robot on a quiet core (6 CC fits), 30–60 s loaded.
e.g.   python -m research.hardware_cv.tendon_zero v6 base,zero,strain
"""
import json
import re
import sys

import numpy as np
import torch
from torch import nn

from dacr_learn.clarke import joint_space_maps
from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.slack import solve_tendon_qp
from dacr_learn.hardware.study.selection import pattern_family, proxy_masks
from dacr_learn.robot import RobotSpec

from .common import RESULTS, ROOT

OUT = RESULTS / "tendon_zero.jsonl"


class TendonCC(CalibratedCC):
    """CalibratedCC with per-tendon zero offsets / gains on the joint displacements."""

    def __init__(self, spec, zero="", gain=False, fixed=None, ridge=None, pull_level=None):
        super().__init__(spec)
        n = self.encoder.g_nominal.shape[0]
        self.zero_mode, self.gain_mode, self.ridge, self.pull_level = zero, gain, ridge, pull_level
        f64 = dict(dtype=torch.float64)
        if zero == "strain":
            self.tendon_zero = nn.Parameter(torch.zeros((), **f64))
        elif zero in ("tendon", "pull"):
            self.tendon_zero = nn.Parameter(torch.zeros(n, **f64))
        elif zero == "segment":
            self.tendon_zero = nn.Parameter(torch.zeros(spec.num_segments, **f64))
        if pull_level is not None and zero != "pull":
            self.pull_zero = nn.Parameter(torch.zeros(n, **f64))   # pull-regime offsets on top of `zero`
        if gain:
            self.tendon_gain = nn.Parameter(torch.zeros(n, **f64))
        self.register_buffer("fixed", torch.zeros(n, **f64) if fixed is None else fixed)

    def offsets(self):
        d = self.fixed
        if self.zero_mode in ("tendon", "pull"):
            d = d + self.tendon_zero - (self.tendon_zero.mean() if self.zero_mode == "tendon" else 0)
        elif self.zero_mode == "strain":   # pretension stretch ∝ path length: p_i = p + s·(L_i − L̄)/L̄
            path = self.encoder.path_length
            d = d + self.tendon_zero * (path / path.mean() - 1)
        elif self.zero_mode == "segment":
            d = d + (self.tendon_zero - self.tendon_zero.mean())[self.encoder.segment_of_joint]
        return d

    def forward(self, x):
        if self.zero_mode == "pull":
            # offsets only in the pull regime: all other tendons parked below pull_level [m]
            regime = ((x < self.pull_level).sum(-1, keepdim=True) >= x.shape[-1] - 1).to(x.dtype)
            xe = x + regime * self.tendon_zero.to(x.dtype)
        else:
            xe = x + self.offsets().to(x.dtype)
            if self.pull_level is not None:
                regime = ((x < self.pull_level).sum(-1, keepdim=True) >= x.shape[-1] - 1).to(x.dtype)
                xe = xe + regime * self.pull_zero.to(x.dtype)
        if self.gain_mode:
            xe = xe * self.tendon_gain.exp().to(x.dtype)
        return self.tip_from_features(self.encoder(xe))


NOISE_MM = 5.0
class AxialCC(TendonCC):
    """Backbone axial compression as m extra generalised coordinates u_k ≥ 0 (shortening of segment k):
    tendon stretch s = x + p − Gρ − C u (C (N, m) path incidence), energy ½ Σ_k (r/l_k) u_k² with
    r = EA_backbone/EA_tendon (1 parameter). Many taut tendons compress the backbone and lower the
    effective pretension of the distal tendons; a single pulled tendon barely does."""

    def __init__(self, spec, zero="", axial=30.0):
        super().__init__(spec, zero=zero)
        self.log_axial = nn.Parameter(torch.tensor(float(axial), dtype=torch.float64).log())
        self.register_buffer("incidence", joint_space_maps(spec).path)

    def forward(self, x):
        enc = self.encoder
        xe = (x + self.offsets().to(x.dtype)).reshape(-1, x.shape[-1]).to(torch.float64)
        g = torch.cat([enc.displacement_map(), self.incidence], -1)
        w = torch.cat([enc.bend_weights(), self.log_axial.exp() / enc.lengths])
        z = solve_tendon_qp(xe + enc.pretension, g, w, 1.0 / enc.path_length)
        rho = z[:, : 2 * spec_m(enc)].reshape(*x.shape[:-1], -1, 2).to(x.dtype)
        return self.tip_from_features(enc.features_from_clarke(rho))

    def compression(self, x):
        enc = self.encoder
        xe = (x + self.offsets().to(x.dtype)).reshape(-1, x.shape[-1]).to(torch.float64)
        g = torch.cat([enc.displacement_map(), self.incidence], -1)
        w = torch.cat([enc.bend_weights(), self.log_axial.exp() / enc.lengths])
        return solve_tendon_qp(xe + enc.pretension, g, w, 1.0 / enc.path_length)[:, 2 * spec_m(enc):]


class SeriesCC(TendonCC):
    """Tendon stiffness 1/(L_i + L0) instead of 1/L_i: a series compliance at the actuator (servo horn,
    spool, connector) worth a tendon length L0 [m] (1 parameter), on top of ``zero`` mode offsets."""

    def __init__(self, spec, zero="", series=0.05):
        super().__init__(spec, zero=zero)
        self.log_series = nn.Parameter(torch.tensor(float(series), dtype=torch.float64).log())

    def forward(self, x):
        enc = self.encoder
        xe = (x + self.offsets().to(x.dtype)).reshape(-1, x.shape[-1]).to(torch.float64)
        w = 1.0 / (enc.path_length + self.log_series.exp())
        rho = solve_tendon_qp(xe + enc.pretension, enc.displacement_map(), enc.bend_weights(), w)
        rho = rho[:, : 2 * spec_m(enc)].reshape(*x.shape[:-1], -1, 2).to(x.dtype)
        return self.tip_from_features(enc.features_from_clarke(rho))


def spec_m(enc):
    return enc.spec.num_segments


SCALES = {"log_axial": 1.0, "log_series": 1.0, "tendon_zero": 1e-3, "pull_zero": 1e-3, "tendon_gain": 0.1}


def make(spec, variant, onsets, slack=-0.01):
    if variant == "base":
        return CalibratedCC(spec)
    if variant == "zero_cal":
        return TendonCC(spec, fixed=-(onsets - onsets.mean()))
    if variant == "strain":
        return TendonCC(spec, zero="strain")
    m = re.fullmatch(r"series(\+strain)?", variant)
    if m:
        return SeriesCC(spec, zero="strain" if m.group(1) else "")
    m = re.fullmatch(r"axial(\d*)(\+strain)?", variant)
    if m:
        return AxialCC(spec, zero="strain" if m.group(2) else "", axial=float(m.group(1) or 30))
    if variant == "strain+pullzero":
        return TendonCC(spec, zero="strain", pull_level=0.5 * slack)
    if variant == "pullzero":
        return TendonCC(spec, zero="pull", pull_level=0.5 * slack)
    ridge = None
    m = re.fullmatch(r"zero_r([\d.]+)", variant)
    if m:
        variant, ridge = "zero", float(m.group(1)) * 1e-3
    parts = variant.split("+")
    zero = "tendon" if "zero" in parts else "segment" if "zero_seg" in parts else ""
    return TendonCC(spec, zero=zero, gain="gain" in parts, ridge=ridge)


def fit(model, x, tip):
    if getattr(model, "ridge", None):
        return fit_ridge(model, x, tip)
    fit_cc(model, x, tip, scales=SCALES)
    return model


def fit_ridge(model, x, tip):
    """Two-stage: fit without prior, then refit with the prior as N pseudo-residual rows (L-BFGS)."""
    fit_cc(model, x, tip, scales=SCALES)
    params = [p for p in model.parameters()]
    opt = torch.optim.LBFGS(params, max_iter=100, line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-16)
    n = x.shape[0]

    def closure():
        opt.zero_grad()
        loss = ((model(x) - tip) ** 2).sum(-1).mean() * 1e6
        # MAP with tip noise σ_n = NOISE_MM: mean |r|² [mm²] + σ_n²/n · Σ (δ/σ)²
        loss = loss + NOISE_MM**2 / n * ((model.offsets() / model.ridge) ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return model


def rmse(model, x, tip):
    with torch.no_grad():
        return round(float(offset_removed_rmse(model(x), tip)) * 1e3, 3)


def load(robot):
    spec = RobotSpec.from_yaml(ROOT / f"configs/robots/ftdcr_{robot}_calibrated.yaml")
    smap = ServoMap.from_yaml(ROOT / f"configs/robots/servo_maps/ftdcr_{robot}_calibrated.yaml")
    rec = load_recording(ROOT / f"data/ftdcr_{robot}/train.csv", spec)
    by_slot = {(s.segment, s.joint): s.servo for s in smap.servos}
    order = [by_slot[(j, i)] for j, seg in enumerate(spec.segments) for i in range(seg.num_joints)]
    onsets = torch.tensor([smap.calibration["servos"][s]["taut_onset_mm"] * 1e-3 for s in order], dtype=torch.float64)
    return spec, smap, rec, order, onsets


def diag(robot, variants):
    spec, smap, rec, order, onsets = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    labels = np.array([re.sub(r"_hold$", "", lab) for lab in rec.labels])
    print("servo order", order, "taut onsets mm", [round(v * 1e3, 2) for v in onsets.tolist()])
    models = {}
    for v in variants:
        models[v] = fit(make(spec, v, onsets, smap.slack_level), x, tip)
        print(v, "train", rmse(models[v], x, tip), json.dumps(models[v].report()))
        if isinstance(models[v], TendonCC):
            with torch.no_grad():
                print("  offsets mm", [round(d * 1e3, 2) for d in models[v].offsets().tolist()],
                      "gains", [round(g, 3) for g in models[v].tendon_gain.exp().tolist()]
                      if models[v].gain_mode else "")
    with torch.no_grad():
        pred = {v: mdl(x) for v, mdl in models.items()}
    print("label".ljust(28), " ".join(v[:10].rjust(10) for v in variants), "  mean residual xyz (first variant) mm")
    for lab in dict.fromkeys(labels):
        sel = torch.from_numpy(labels == lab)
        errs = [float(((pred[v][sel] - tip[sel]) ** 2).sum(-1).mean().sqrt()) * 1e3 for v in variants]
        mean_res = ((tip[sel] - pred[variants[0]][sel]).mean(0) * 1e3).tolist()
        print(lab[:28].ljust(28), " ".join(f"{e:10.2f}" for e in errs), [round(r, 1) for r in mean_res])


def score(robot, variant, pull_test=True):
    """Train / CV / extrap [mm]; pull_test=False (information only, not a selection proxy): the
    single-tendon pull rows are dropped from every test set (they are in the CV's single fold)."""
    spec, smap, rec, order, onsets = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    keep = np.array([pull_test or not re.search(r"tendon\d+", lab) for lab in rec.labels])
    full = fit(make(spec, variant, onsets, smap.slack_level), x, tip)
    out = {"robot": robot, "variant": variant, "train": rmse(full, x, tip)}
    if not pull_test:
        out["test_rows"] = "without pull rows (information only)"
    if isinstance(full, TendonCC):
        out["offsets_mm"] = [round(d * 1e3, 2) for d in full.offsets().tolist()]
        if full.gain_mode:
            out["gains"] = [round(g, 3) for g in full.tendon_gain.exp().tolist()]
    for proxy, folds in proxy_masks(rec.labels).items():
        per = {}
        for name, tr, te in folds:
            tr, te = torch.from_numpy(tr), torch.from_numpy(te & keep)
            per[name] = rmse(fit(make(spec, variant, onsets, smap.slack_level), x[tr], tip[tr]), x[te], tip[te])
        out[proxy], out[proxy + "_folds"] = round(float(np.mean(list(per.values()))), 3), per
    print(json.dumps(out), flush=True)
    with OUT.open("a") as f:
        f.write(json.dumps(out) + "\n")


def subsets(robot, variants):
    """Fit on subsets of train (pulls, single-segment patterns without pulls, pair12, all patterns, all)
    and report the RMSE [mm] on every subset plus the fitted radii, compliance and per-segment
    pretension: which parts of the recording a CC model can fit together (results/tendon_zero_subsets.jsonl)."""
    spec, smap, rec, order, onsets = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    fam = np.array([pattern_family(lab) for lab in rec.labels])
    pull = np.array([bool(re.search(r"tendon\d+", lab)) for lab in rec.labels])
    parts = {"pulls": pull, "singles_no_pulls": (fam == "single") & ~pull, "pair12": fam == "pair12",
             "pair13": fam == "pair13", "pair23": fam == "pair23"}
    fits = {**parts, "singles": fam == "single", "singles_no_pulls+pair12": parts["singles_no_pulls"] | parts["pair12"],
            "patterns": ~pull, "pairs": fam != "single", "all": np.ones_like(pull)}
    for v in variants:
        for name, sel in fits.items():
            if name in ("pair13", "pair23"):
                continue
            mdl = fit(make(spec, v, onsets, smap.slack_level), x[torch.from_numpy(sel)], tip[torch.from_numpy(sel)])
            with torch.no_grad():
                seg_p = (mdl.encoder.pretension + mdl.offsets()[0::3] if isinstance(mdl, TendonCC)
                         else mdl.encoder.pretension.expand(spec.num_segments)) * 1e3
            r = mdl.report()
            on = {k: rmse(mdl, x[torch.from_numpy(q)], tip[torch.from_numpy(q)]) for k, q in parts.items()}
            out = {"robot": robot, "variant": v, "fit_on": name, "rmse_on": on,
                   "radius_mm": r["effective_radius_mm"], "compliance_mm2": r["compliance_EI_over_EA_mm2"],
                   "segment_pretension_mm": [round(float(p), 3) for p in seg_p]}
            print(json.dumps(out), flush=True)
            with OUT.with_name("tendon_zero_subsets.jsonl").open("a") as f:
                f.write(json.dumps(out) + "\n")


def main() -> None:
    torch.set_num_threads(1)
    robot, variants = sys.argv[1], sys.argv[2].split(",")
    if "--diag" in sys.argv:
        diag(robot, variants)
    elif "--subsets" in sys.argv:
        subsets(robot, variants)
    else:
        for v in variants:
            score(robot, v, pull_test="--no-pull-test" not in sys.argv)


if __name__ == "__main__":
    main()
