"""Prandtl-Ishlinskii (PI) variants of the per-segment residual model, cross-validated on the
training families. cfg keys: "mem" (memory input widths [m]), "hidden", "pi" (play widths whose
softmax-weighted sum is the CC input), "pi_seg", "lin" (widths of the stop-operator term
sum_j c_kj (rho - play_wj(rho))), "lin_mat". ~45 s per config and seed.
(results/pi_hysteresis.jsonl was produced by an earlier copy of this script with the same model code.)

Numbers: docs/history/hardware.md, "2026-11-21: Tried after the first results".
Run from the repository root: python -m research.hardware_cv.pi_hysteresis '{"lin6": {"mem": [], "hidden": 64,
"pi": [], "lin": [5e-5, 1e-4, 2e-4, 4e-4, 8e-4]}}' 0,1,2
"""

import json
import sys
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.learned import DEPTH, RESIDUAL_RHO_SCALE, play_operator, train_full_batch
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.models import mlp

from .common import FOLDS, setup
from .common import fit as cc_for


def plays(rho, widths):
    return torch.stack([rho if w == 0 else play_operator(rho, w) for w in widths], 0)  # (J, n, m, 2)


class Model(nn.Module):
    """CC + per-segment residual. mode: 'mem' (memory inputs for mem_widths) and/or PI input."""

    def __init__(self, cc, feats, pl, cfg):
        super().__init__()
        self.cc, self.cfg = cc, cfg
        m = feats.shape[-2]
        self.register_buffer("rho_std", feats[..., :2].float().std())
        self.register_buffer("onehot", torch.eye(m))
        nmem = len(cfg["mem"])
        self.net = mlp(2 + 2 * nmem + m, 2, cfg["hidden"], DEPTH, "silu")
        if cfg["pi"]:
            J = len(cfg["pi"])
            self.logit = nn.Parameter(torch.zeros(m if cfg.get("pi_seg", True) else 1, J))
        if cfg.get("lin"):
            J = len(cfg["lin"])
            self.c = nn.Parameter(torch.zeros(m, J, 2, 2) if cfg.get("lin_mat") else torch.zeros(m, J))

    def forward(self, feats, pl_pi, mem, lin=None):
        rho = feats[..., :2].float()
        if self.cfg["pi"]:
            w = torch.softmax(self.logit, -1)  # (m|1, J)
            rho_in = torch.einsum("jnmc,mj->nmc", pl_pi.float(), w.expand(rho.shape[-2], -1))
        else:
            rho_in = rho
        parts = [rho_in / self.rho_std] + [mm.float() for mm in mem]
        inp = torch.cat(parts + [self.onehot.expand(*rho.shape[:-1], -1)], -1)
        delta = self.net(inp) * RESIDUAL_RHO_SCALE
        if self.cfg.get("lin"):
            d = lin.float()  # (J, n, m, 2) = rho - play
            if self.cfg.get("lin_mat"):
                delta = delta + torch.einsum("jnmc,mjdc->nmd", d, self.c)
            else:
                delta = delta + torch.einsum("jnmc,mj->nmc", d, self.c)
        f = feats.float()
        return self.cc.tip_from_features(torch.cat([rho_in + delta, f[..., 2:]], -1)).double()


def prep(cc, x, cfg):
    with torch.no_grad():
        feats = cc.encoder(x)
        rho = feats[..., :2]
        pl_pi = plays(rho, cfg["pi"]) if cfg["pi"] else None
        mem = [(rho - play_operator(rho, w)) / w for w in cfg["mem"]]
        lin = (rho.unsqueeze(0) - plays(rho, cfg["lin"])) if cfg.get("lin") else None
    return feats, pl_pi, mem, lin


def run(cfg, cc, x_all, tip_all, tr, te, seed, steps=1500):
    feats, pl, mem, lin = prep(cc, x_all, cfg)

    def sel(idx):
        return (
            feats[idx],
            None if pl is None else pl[:, idx],
            [mm[idx] for mm in mem],
            None if lin is None else lin[:, idx],
        )

    torch.manual_seed(seed)
    model = Model(cc, feats[tr], pl, cfg)
    a = sel(tr)
    ttr = tip_all[tr]
    params = list(model.net.parameters()) + ([model.logit] if cfg["pi"] else []) + ([model.c] if cfg.get("lin") else [])
    train_full_batch(params, lambda: (model(*a) - ttr).pow(2).mean() / 1e-6, steps=steps)
    with torch.no_grad():
        b = sel(te)
        pred = model(*b)
        out = {"rmse": float(offset_removed_rmse(pred, tip_all[te])) * 1e3}
        if cfg["pi"]:
            out["w"] = torch.softmax(model.logit, -1).tolist()
        if cfg.get("lin"):
            out["w"] = model.c.tolist()
    return out


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    fam = d.fam
    cfgs = json.loads(sys.argv[1])
    seeds = [int(s) for s in sys.argv[2].split(",")]
    x_all = d.smap.displacements(d.spec, d.train_rec)
    tip = d.train_rec.tip
    ccs = {}
    for f in FOLDS:
        tr = torch.from_numpy(fam != f)
        ccs[f] = cc_for(x_all[tr], tip[tr])
    for name, cfg in cfgs.items():
        t0 = time.time()
        scores = []
        ws = []
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            te = ~tr
            for s in seeds:
                r = run(cfg, ccs[f], x_all, tip, tr, te, s)
                scores.append((f, s, r["rmse"]))
                ws.append(r.get("w"))
        per = {f: np.mean([r for ff, s, r in scores if ff == f]) for f in FOLDS}
        print(
            json.dumps(
                {
                    "name": name,
                    "cv_mean": float(np.mean(list(per.values()))),
                    "per_fold": {k: round(v, 3) for k, v in per.items()},
                    "sec": round(time.time() - t0, 1),
                    "w_last": ws[-1],
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
