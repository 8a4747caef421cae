"""CC + per-segment Clarke residual network with a play-operator memory input (model (g)
``cc_clarke_residual_history``) and optional linear hysteresis terms whose gain grows with the bends of the
other segments (features 'own', 'prox', 'dist', 'own*prox', 'total'). With "equivariant": true the
network sees ρ and the memory in each segment's bending-direction frame (radial, tangential) and
outputs the correction in it: a correction that is the same for every bending direction.
CV (default), EXTRAP (fit on single segments, test on all pairs) or VAL (FTDCR v4's val.csv);
~80 s per config (2 seeds).

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (rows `residual_memory.py`) and "2026-11-21: Third round: static physics and
a better selection proxy" (equivariant, 32 / 128 units; EXTRAP of (g)).
Run from the repository root: python -m research.hardware_cv.residual_memory '{"name": {"width": 1e-4,
"mem_in": true, "lin": ["total"], "c0": true}}' 0,1 [CV|EXTRAP|VAL] [tendon_play=5e-5]
"""

import json
import sys
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.learned import DEPTH, RESIDUAL_RHO_SCALE, play_operator, train_full_batch
from dacr_learn.models import mlp

from .common import FOLDS, fit, rmse, setup, tendon_play, val_data

EQUI_EPS = 1e-4  # [m] below this bend (in ρ units) the bending-direction frame fades out


class Model(nn.Module):
    def __init__(self, cc, feats_tr, cfg):
        super().__init__()
        self.cc, self.cfg = cc, cfg
        m = feats_tr.shape[-2]
        self.register_buffer("rho_std", feats_tr[..., :2].float().std())
        self.register_buffer("onehot", torch.eye(m))
        self.net = mlp(2 + 2 * bool(cfg["mem_in"]) + m, 2, cfg.get("hidden", 64), DEPTH, "silu")
        self.c0 = nn.Parameter(torch.zeros(m))
        self.c = nn.Parameter(torch.zeros(len(cfg["lin"])))
        self.cs = nn.Parameter(torch.zeros(m, len(cfg.get("lin_static", []))))

    def forward(self, feats, mem, amp):
        rho = feats[..., :2].float()
        if self.cfg.get("equivariant"):  # inputs and output in each segment's bending-direction frame
            e1 = rho / (rho.pow(2).sum(-1, keepdim=True) + EQUI_EPS**2).sqrt()  # ≈ unit bend direction
            e2 = torch.stack([-e1[..., 1], e1[..., 0]], -1)

            def local(v):
                return torch.stack([(v * e1).sum(-1), (v * e2).sum(-1)], -1)

            parts = [local(rho) / self.rho_std] + ([local(mem.float())] if self.cfg["mem_in"] else [])
            inp = torch.cat(parts + [self.onehot.expand(*rho.shape[:-1], -1)], -1)
            out = self.net(inp) * RESIDUAL_RHO_SCALE
            delta = out[..., :1] * e1 + out[..., 1:] * e2
        else:
            parts = [rho / self.rho_std] + ([mem.float()] if self.cfg["mem_in"] else [])
            inp = torch.cat(parts + [self.onehot.expand(*rho.shape[:-1], -1)], -1)
            delta = self.net(inp) * RESIDUAL_RHO_SCALE
        if self.cfg["lin"]:
            a = amp[..., : len(self.cfg["lin"])].float()
            gain = self.c0 + (a * self.c).sum(-1) if self.cfg["c0"] else (a * self.c).sum(-1)  # (n, m)
            delta = delta + gain.unsqueeze(-1) * mem.float() * RESIDUAL_RHO_SCALE
        if self.cfg.get("lin_static"):
            unit = rho / rho.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            gain = (amp[..., len(self.cfg["lin"]) :].float() * self.cs).sum(-1)
            delta = delta + gain.unsqueeze(-1) * unit * RESIDUAL_RHO_SCALE
        f = feats.float()
        return self.cc.tip_from_features(torch.cat([rho + delta, f[..., 2:]], -1)).double()


def prep(cc, x, cfg):
    radius = setup().radius
    with torch.no_grad():
        feats = cc.encoder(x)
        rho = feats[..., :2]
        w = cfg["width"]
        mem = (rho - play_operator(rho, w)) / w
        th = rho.norm(dim=-1) / radius  # (n, m)
        prox = torch.cat([torch.zeros_like(th[:, :1]), th.cumsum(-1)[:, :-1]], -1)
        dist = th.flip(-1).cumsum(-1).flip(-1) - th
        unit = rho / rho.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        aligned = torch.einsum("nkc,njc->nk", unit, rho / radius[:, None]) - th  # Σ_{j≠k} ρ̂_k·ρ_j/d [rad]
        names = {
            "own": th,
            "prox": prox,
            "dist": dist,
            "own*prox": th * prox,
            "total": th.sum(-1, keepdim=True).expand_as(th),
            "aligned": aligned,
            "aligned+": aligned.clamp_min(0),
        }
        keys = list(cfg["lin"]) + list(cfg.get("lin_static", []))
        amp = torch.stack([names[k] for k in keys], -1) if keys else th.new_zeros(*th.shape, 0)
    return feats, mem, amp


def fit_predict(cfg, cc, x_all, tip_all, tr, te, seed, steps=1500):
    """Train the model on rows ``tr`` of a recording (history runs along all rows); returns the
    model and its tip predictions (float64, m) on rows ``te``."""
    feats, mem, amp = prep(cc, x_all, cfg)
    torch.manual_seed(seed)
    model = Model(cc, feats[tr], cfg)
    a = (feats[tr], mem[tr], amp[tr])
    ttr = tip_all[tr]
    train_full_batch(list(model.parameters()), lambda: (model(*a) - ttr).pow(2).mean() / 1e-6, steps=steps)
    with torch.no_grad():
        return model, model(feats[te], mem[te], amp[te])


def run(cfg, cc, x_all, tip_all, tr, te, seed, steps=1500):
    model, pred = fit_predict(cfg, cc, x_all, tip_all, tr, te, seed, steps)
    return rmse(pred, tip_all[te]), model.c0.tolist() + model.c.tolist() + model.cs.flatten().tolist()


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    cfgs = json.loads(sys.argv[1])
    seeds = [int(s) for s in sys.argv[2].split(",")]
    do_val = len(sys.argv) > 3 and sys.argv[3] == "VAL"
    x_raw = x_tr
    tendon_w = float(dict(a.split("=") for a in sys.argv[4:] if "=" in a).get("tendon_play", 0))
    if tendon_w:  # commands through a tendon-space play first (the whole recording, causal)
        x_tr = tendon_play(x_tr, tendon_w)
    ccs = (
        {f: fit(x_tr[torch.from_numpy(fam != f)], tip_tr[torch.from_numpy(fam != f)]) for f in FOLDS}
        if sys.argv[3:4] in ([], ["CV"])
        else {}
    )
    for name, cfg in cfgs.items():
        t0 = time.time()
        if do_val:
            x_va, tip_va = val_data()
            x_all, tip_all = torch.cat([x_tr, x_va]), torch.cat([tip_tr, tip_va])
            if tendon_w:
                x_all = torch.cat([x_tr, tendon_play(torch.cat([x_raw, x_va]), tendon_w)[len(x_raw) :]])
            cc = fit(x_all[: len(x_tr)], tip_tr)
            tr = torch.arange(len(x_all)) < len(x_tr)
            res = [run(cfg, cc, x_all, tip_all, tr, ~tr, s) for s in seeds]
            print(
                json.dumps(
                    {
                        "name": name,
                        "VAL": [round(r[0], 3) for r in res],
                        "val_mean": round(float(np.mean([r[0] for r in res])), 3),
                        "coef": [round(c, 3) for c in res[-1][1]],
                        "s": round(time.time() - t0, 1),
                    }
                ),
                flush=True,
            )
            continue
        if len(sys.argv) > 3 and sys.argv[3] == "EXTRAP":  # singles → pairs: an extrapolation in the number of segments
            tr = torch.from_numpy(fam == "single")
            cc = fit(x_tr[tr], tip_tr[tr])
            res = [run(cfg, cc, x_tr, tip_tr, tr, ~tr, s) for s in seeds]
            print(
                json.dumps(
                    {
                        "name": name,
                        "singles_to_pairs": round(float(np.mean([r[0] for r in res])), 3),
                        "per_seed": [round(r[0], 3) for r in res],
                        "s": round(time.time() - t0, 1),
                    }
                ),
                flush=True,
            )
            continue
        scores = []
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            for s in seeds:
                r, coef = run(cfg, ccs[f], x_tr, tip_tr, tr, ~tr, s)
                scores.append((f, r))
        per = {f: float(np.mean([r for ff, r in scores if ff == f])) for f in FOLDS}
        print(
            json.dumps(
                {
                    "name": name,
                    "cv": round(float(np.mean(list(per.values()))), 3),
                    "folds": {k: round(v, 2) for k, v in per.items()},
                    "coef": [round(c, 3) for c in coef],
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
