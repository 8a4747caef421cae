"""Why a held distal segment bends back more on FTDCR v6 than the CC model allows (issue 12, research).

Finding 3 of the fourth round (docs/history/hardware.md): on v6 the single-segment patterns and pair12 want
different CC parameters. In ``pair12_opp_*`` segment 1's tendons are pulled while segment 2's and 3's
are held near 0: segment 2 is bent back only by the coupled routing (its tendons pass through the
bent segment 1), an S-curve. The singles fit predicts a much larger tip excursion than measured.

``--diag``: the CC model fitted on the single-segment family, on every pair12 / seg1 / seg2 pattern:
RMSE, measured and predicted tip excursion, the model's peak bend of each segment, and the
bend scales (a₁, a₂) of segments 1, 2 (segment 3 as the model says, pattern offset free) that fit
the measured tips best: a₁ < 1 ⇔ segment 1 bends less than predicted, a₂ the same for segment 2.

Candidates (static; each a subclass of the package model with the robot's chosen CC variant as the
base: v4 ``strain``, v6 ``base``; the extra parameters start at 0 from the base fit):

- ``capstan``: Coulomb/capstan friction of every tendon along its path, static (loading): the tension
  a tendon applies in sub-arc j is T·(1 − μ·W_j), W_j the bend from the base to the middle of
  sub-arc j (frictionless shape); μ signed, fitted (+1). The distal tendons lose (μ > 0) or gain
  tension in the bent proximal segment, so they act on segment 2 differently from segment 1.
- ``capstan2``: the same with every segment split into two sub-arcs that share the tendons (their
  bends differ only through friction): non-constant curvature along the long 100 mm segments,
  segment 1's distal half seeing the distal tendons' tension differently (+1).
- ``gravity`` / ``gravity2``: the backbone's own weight as an external load in the tendon force balance
  (one step at the gravity-free shape, sign fitted: upright or hanging), on 1 or 2 sub-arcs per
  segment; the 222 mm v6 robot is long, and the load bends the halves differently (+1).
- ``lock``: friction locks each tendon in the discs, so the stretch imposed at the actuator spreads over
  the free length L₀ below the base as well as the path L_i, while the stretch the bending imposes inside
  the robot does not: tension ∝ (x_i + p_i)/(L_i + L₀) − (Gρ)_i/L_i, i.e. the commands (and pretension)
  scaled by L_i/(L_i + L₀) = 1/(1 + λ·L̄/L_i), λ = L₀/L̄ fitted (+1). A pulled proximal tendon is softer
  than a held distal one that segment 1's bend stretches from inside.
- ``distal``: the stiffness of a tendon grows with the number of segments it passes,
  w_i = exp(τ·(k_i − 1))/L_i (+1): friction "locks" a tendon in the proximal discs, so a held distal
  tendon is stiffer than its free length says (τ = 0: the base model; the ``series`` compliance of the
  fourth round is the opposite direction of the same family).
- ``axial``: backbone axial compression (``tendon_zero.AxialCC``, r = EA_backbone/EA_tendon fitted, +1; with
  the strain pretension on v4 as ``axial+strain`` there): in ``pair12_opp`` the pulled tendon must also
  drive segment 2 back through the held distal tendon, about twice the tension of a single pattern, and
  a shortening backbone would absorb part of its command — segment 1 bends less at the same command.

Rule fixed before scoring (brief): a candidate counts only if it improves v6's singles → pairs score
(``extrap``) by ≥ 0.20 mm AND worsens neither v4's singles → pairs nor v4's family CV (``cv``) by more
than 0.10 mm, each robot on its chosen CC variant. Both proxies are reported on both robots.

Numbers: docs/history/hardware.md, "v6's pair12 inconsistency (same round, no change)" in "2026-11-23:
Fourth round: pretension that grows with the tendon length, chosen per robot" (results/pair_coupling.jsonl).
Run from the repository root:

    python -m research.hardware_cv.pair_coupling ROBOT VARIANTS [--diag | --reconcile | --extrap-only]
        [--extra-scale=S]  (the fit scale of the extra parameter, default 0.05; the results use 1)

→ one JSON line per variant and robot (train, cv, extrap [mm], per fold, fitted extra parameter on
all of train and on the singles fold) appended to results/pair_coupling.jsonl. ~30 s per variant and
robot, loaded.
"""
import json
import re
import sys

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.slack import solve_tendon_qp
from dacr_learn.hardware.study.selection import pattern_family, proxy_masks
from dacr_learn.kinematics import backbone_points, forward_kinematics
from dacr_learn.robot import RobotSpec

from .common import RESULTS
from .tendon_zero import SCALES as TENDON_ZERO_SCALES
from .tendon_zero import AxialCC, load, rmse

OUT = RESULTS / "pair_coupling.jsonl"
CHOSEN = {"v4": {"pretension_strain": True}, "v6": {}}          # selection.choose_cc_variant's picks
SCALES = {"extra": 0.05, "gravity": 1e-5}
GRAVITY_POINTS = 4                                                 # backbone points per sub-arc
EXTRA_SCALE: float | None = None                                   # --extra-scale=S, set by main()


def split_spec(spec: RobotSpec, parts: int) -> RobotSpec:
    """The same robot with every segment cut into ``parts`` equal sub-arcs (for the kinematics only)."""
    d = spec.to_dict()
    d["segments"] = [{**s, "length": s["length"] / parts} for s in d["segments"] for _ in range(parts)]
    return RobotSpec.from_dict(d)


class CouplingCC(CalibratedCC):
    """CalibratedCC with one extra physical parameter (``kind``: capstan, gravity, distal) on ``parts``
    sub-arcs per segment. With the extra parameter at 0 it equals the package model (any ``parts``)."""

    def __init__(self, spec, kind, parts=1, **options):
        super().__init__(spec, **options)
        self.kind, self.parts = kind, parts
        self.sub_spec = split_spec(spec, parts)
        name = "gravity" if kind == "gravity" else "extra"
        setattr(self, name, nn.Parameter(torch.zeros((), dtype=torch.float64)))
        self.param_name = name
        seg = self.encoder.segment_of_joint
        self.register_buffer("passed", (seg + 1).to(torch.float64), persistent=False)   # segments tendon i passes

    def sub_system(self):
        """G (N, D), bending weights (D,), tendon weights (N,) on the sub-arc Clarke coordinates."""
        enc, m, k = self.encoder, self.spec.num_segments, self.parts
        g = enc.displacement_map().unflatten(-1, (m, 2)).repeat_interleave(k, dim=-2).flatten(-2)
        bend_w = enc.bend_weights().unflatten(-1, (m, 2)).repeat_interleave(k, dim=-2).flatten() * k
        tendon_w = 1.0 / enc.path_length
        if self.kind == "distal":
            tendon_w = tendon_w * torch.exp(self.extra * (self.passed - 1))
        return g, bend_w, tendon_w

    def sub_features(self, rho):
        """Sub-arc Clarke coordinates (B, D) at the effective radii → features (B, m·parts, 4), nominal convention."""
        enc, k = self.encoder, self.parts
        scale = (enc.radius / enc.effective_radius()).repeat_interleave(k).to(rho.dtype)
        rho = rho.unflatten(-1, (-1, 2)) * scale.unsqueeze(-1)
        beta = torch.tensor([s.length for s in self.sub_spec.segments], dtype=rho.dtype).expand(rho.shape[:-1])
        return torch.cat([rho, beta.unsqueeze(-1), torch.zeros_like(beta).unsqueeze(-1)], -1)

    def wrap(self, rho):
        """Bend [rad] from the base to the middle of each sub-arc (B, m·parts)."""
        d = self.encoder.effective_radius().repeat_interleave(self.parts).to(rho.dtype)
        th = rho.unflatten(-1, (-1, 2)).norm(dim=-1) / d
        return th.cumsum(-1) - th / 2

    def gravity_force(self, rho):
        """−∂Z/∂ρ (B, D) at ρ: Z the summed mocap height of backbone points (after the base tilt)."""
        with torch.enable_grad():
            r = rho.detach().requires_grad_(True)
            pts = backbone_points(self.sub_spec, self.sub_features(r), GRAVITY_POINTS)
            z = (pts @ self.base_rotation().detach().to(pts.dtype).mT)[..., 2].sum()
            return -torch.autograd.grad(z, r)[0]

    def forward(self, x):
        enc = self.encoder
        flat = x.reshape(-1, x.shape[-1]).to(torch.float64) + enc.tendon_pretension()
        if self.kind == "lock":
            flat = flat / (1 + self.extra * enc.path_length.mean() / enc.path_length)
        g, bend_w, tendon_w = self.sub_system()
        force_map, load = None, None
        if self.kind in ("capstan", "gravity"):
            with torch.no_grad():
                rho0 = solve_tendon_qp(flat, g, bend_w, tendon_w)
            if self.kind == "capstan":
                factor = 1 - self.extra * self.wrap(rho0)                       # (B, m·parts)
                force_map = g * factor.repeat_interleave(2, -1).unsqueeze(-2)
            else:
                load = self.gravity * self.gravity_force(rho0)
        rho = solve_tendon_qp(flat, g, bend_w, tendon_w, force_map=force_map, load=load)
        feats = self.sub_features(rho).reshape(*x.shape[:-1], -1, 4).to(x.dtype)
        return self.to_world(self.marker_point(forward_kinematics(self.sub_spec, feats)))


def make(spec, robot, variant):
    if variant == "base":
        return CalibratedCC(spec, **CHOSEN[robot])
    m = re.fullmatch(r"(capstan|gravity|distal|lock)(\d?)", variant)
    if not m:
        raise ValueError(f"variant {variant!r}: expected base, capstan[2], gravity[2], distal or lock")
    return CouplingCC(spec, m.group(1), int(m.group(2) or 1), **CHOSEN[robot])


def fit(spec, robot, variant, x, tip):
    """Base fit, then (for a candidate) the full fit from it with the extra parameter starting at 0."""
    base = CalibratedCC(spec, **CHOSEN[robot])
    fit_cc(base, x, tip)
    if variant == "base":
        return base
    if variant == "axial":                       # tendon_zero's model, its start (r = 30) and scales
        model = AxialCC(spec, zero="strain" if CHOSEN[robot] else "")
        fit_cc(model, x, tip, scales=TENDON_ZERO_SCALES)
        return model
    name, _, start = variant.partition("@")          # "capstan@-10": the extra parameter starts at −10
    model = make(spec, robot, name)
    model.load_state_dict({**base.state_dict(), model.param_name: torch.tensor(float(start or 0), dtype=torch.float64)})
    fit_cc(model, x, tip, scales={**SCALES, **({"extra": EXTRA_SCALE} if EXTRA_SCALE else {})})
    return model


def extra_value(model):
    if isinstance(model, AxialCC):               # r = EA_backbone / EA_tendon
        return round(float(model.log_axial.detach().exp()), 4)
    return round(float(getattr(model, model.param_name).detach()), 6) if isinstance(model, CouplingCC) else None


def by_family(model, x, tip, labels, rows):
    """RMSE [mm] per pattern family of the test rows, with the offset removed over all test rows."""
    with torch.no_grad():
        res = model(x) - tip
    res = res - res.mean(0)
    fam = np.array([pattern_family(lab) for lab, r in zip(labels, rows, strict=True) if r])
    return {f: round(float(res[torch.from_numpy(fam == f)].pow(2).sum(-1).mean().sqrt()) * 1e3, 3)
            for f in sorted(set(fam))}


def score(robot, variant, proxies=("cv", "extrap")):
    spec, smap, rec, _, _ = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    full = fit(spec, robot, variant, x, tip)
    out = {"robot": robot, "cc_variant": "strain" if CHOSEN[robot] else "base", "variant": variant,
           "extra_scale": EXTRA_SCALE or SCALES["gravity" if variant.startswith("gravity") else "extra"],
           "train": rmse(full, x, tip), "extra_all": extra_value(full), "report": full.report()}
    for proxy, folds in proxy_masks(rec.labels, proxies).items():
        per = {}
        for name, tr, te in folds:
            tr, te = torch.from_numpy(tr), torch.from_numpy(te)
            mdl = fit(spec, robot, variant, x[tr], tip[tr])
            per[name] = rmse(mdl, x[te], tip[te])
            out[f"extra_{proxy}_{name}"] = extra_value(mdl)
            if proxy == "extrap":
                out["extrap_by_family"] = by_family(mdl, x[te], tip[te], rec.labels, te.numpy())
        out[proxy], out[proxy + "_folds"] = round(float(np.mean(list(per.values()))), 3), per
    print(json.dumps(out), flush=True)
    with OUT.open("a") as f:
        f.write(json.dumps(out) + "\n")


def bend_scales(model, rho, tip):
    """Scales (a₁, a₂) of segment 1's and 2's bends and a tip offset that best fit ``tip`` (n, 3) [m]."""
    s = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    off = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([s, off], max_iter=100, line_search_fn="strong_wolfe")

    def pred():
        scale = torch.cat([s.exp(), s.new_ones(rho.shape[-2] - 2)])
        return model.tip_from_features(model.encoder.features_from_clarke(rho * scale[:, None])) + off * 1e-3

    def closure():
        opt.zero_grad()
        loss = ((pred() - tip) ** 2).sum(-1).mean() * 1e6
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        return s.exp().tolist(), float(((pred() - tip) ** 2).sum(-1).mean().sqrt()) * 1e3


def diag(robot, variants):
    spec, smap, rec, _, _ = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    fam = np.array([pattern_family(lab) for lab in rec.labels])
    labels = np.array([re.sub(r"_hold$", "", lab) for lab in rec.labels])
    single = torch.from_numpy(fam == "single")
    for v in variants:
        mdl = fit(spec, robot, v, x[single], tip[single])
        print(v, "fitted on singles:", json.dumps(mdl.report()), "extra", extra_value(mdl))
        with torch.no_grad():
            rho, pred = mdl.encoder.clarke(x), mdl(x)
        keep = [lab for lab in dict.fromkeys(labels) if re.search(r"pair12|_seg[12]_", lab)]
        for lab in keep:
            sel = torch.from_numpy(labels == lab)
            meas = float((tip[sel] - tip[sel][:1]).norm(dim=-1).max()) * 1e3
            prd = float((pred[sel] - pred[sel][:1]).norm(dim=-1).max()) * 1e3
            theta = (rho[sel].norm(dim=-1) / mdl.encoder.effective_radius()).max(0).values
            scales, after = bend_scales(mdl, rho[sel], tip[sel]) if v == "base" else ([], float("nan"))
            print(f"  {lab[5:]:22s} n={int(sel.sum()):3d} rmse {rmse(mdl, x[sel], tip[sel]):6.2f}  excursion meas "
                  f"{meas:6.1f} pred {prd:6.1f}  bend max {[round(float(t), 2) for t in theta]}  a1,a2 "
                  f"{[round(a, 2) for a in scales]} rmse {after:5.2f}")


def reconcile(robot, variants):
    """Information only (not a proxy): fit on the single-segment patterns without the tendon pulls, on
    pair12, and on both; RMSE [mm] on each part. A candidate that is the missing physics lets the joint
    fit approach the separate fits (base on v6: 5.89 / 7.44 joint vs 4.34 / 5.03 separate)."""
    spec, smap, rec, _, _ = load(robot)
    x, tip = smap.displacements(spec, rec), rec.tip
    fam = np.array([pattern_family(lab) for lab in rec.labels])
    pull = np.array([bool(re.search(r"tendon\d+", lab)) for lab in rec.labels])
    parts = {"singles_no_pulls": (fam == "single") & ~pull, "pair12": fam == "pair12"}
    fits = {**parts, "both": parts["singles_no_pulls"] | parts["pair12"]}
    for v in variants:
        out = {"robot": robot, "variant": v, "mode": "reconcile (information only)", "extra_scale": EXTRA_SCALE}
        for name, sel in fits.items():
            mdl = fit(spec, robot, v, x[torch.from_numpy(sel)], tip[torch.from_numpy(sel)])
            out[f"fit_{name}"] = {k: rmse(mdl, x[torch.from_numpy(q)], tip[torch.from_numpy(q)])
                                  for k, q in parts.items()}
            out[f"fit_{name}"].update(extra=extra_value(mdl), radius_mm=mdl.report()["effective_radius_mm"],
                                      compliance_mm2=mdl.report()["compliance_EI_over_EA_mm2"])
        print(json.dumps(out), flush=True)
        with OUT.open("a") as f:
            f.write(json.dumps(out) + "\n")


def main() -> None:
    global EXTRA_SCALE
    torch.set_num_threads(1)
    EXTRA_SCALE = next((float(a.split("=")[1]) for a in sys.argv if a.startswith("--extra-scale=")), None)
    robot, variants = sys.argv[1], sys.argv[2].split(",")
    if "--diag" in sys.argv:
        diag(robot, variants)
    elif "--reconcile" in sys.argv:
        reconcile(robot, variants)
    else:
        for v in variants:
            score(robot, v, ("extrap",) if "--extrap-only" in sys.argv else ("cv", "extrap"))


if __name__ == "__main__":
    main()
