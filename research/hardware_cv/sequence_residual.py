"""Model (e) plus a learned recurrent memory: a GRU per segment (weights shared, segment one-hot)
runs along the recording on that segment's Clarke coordinates and their step changes, and its
output is added to the static per-segment Clarke correction before the CC kinematics. Trained on
windows (warm-up rows without loss, then loss rows of the training families), evaluated by
running the GRU causally along the whole recording (VAL: FTDCR v4's val.csv). ~6 min (1 seed).

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `sequence_residual.py`: 16 / 32 units).
Run from the repository root: python -m research.hardware_cv.sequence_residual HIDDEN SEEDS [CV|VAL]
e.g.   python -m research.hardware_cv.sequence_residual 16 0 CV
"""

import json
import sys
import time

import numpy as np
import torch
from torch import nn

from dacr_learn.hardware.learned import DEPTH, RESIDUAL_RHO_SCALE
from dacr_learn.models import mlp

from .common import FOLDS, fit, rmse, setup, val_data

WARMUP, WINDOW, STEPS, LR = 32, 64, 1500, 3e-3


class SeqResidual(nn.Module):
    def __init__(self, cc, feats_tr, hidden):
        super().__init__()
        self.cc = cc
        m = feats_tr.shape[-2]
        rho = feats_tr[..., :2].float()
        self.register_buffer("rho_std", rho.std())
        self.register_buffer("step_std", rho.diff(dim=0).std())
        self.register_buffer("onehot", torch.eye(m))
        self.static = mlp(2 + m, 2, 64, DEPTH, "silu")
        self.gru = nn.GRU(4 + m, hidden, batch_first=True)
        self.head = nn.Linear(hidden, 2)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, feats):
        """feats (B, T, m, 4) sequences → tips (B, T, 3)."""
        rho = feats[..., :2].float()
        step = torch.cat([torch.zeros_like(rho[:, :1]), rho.diff(dim=1)], 1)
        hot = self.onehot.expand(*rho.shape[:-1], -1)
        static = self.static(torch.cat([rho / self.rho_std, hot], -1))
        seq_in = torch.cat([rho / self.rho_std, step / self.step_std, hot], -1)  # (B, T, m, 4+m)
        b, t, m = seq_in.shape[:3]
        out, _ = self.gru(seq_in.transpose(1, 2).reshape(b * m, t, -1))
        dyn = self.head(out).reshape(b, m, t, 2).transpose(1, 2)
        delta = (static + dyn) * RESIDUAL_RHO_SCALE
        f = feats.float()
        return self.cc.tip_from_features(torch.cat([rho + delta, f[..., 2:]], -1)).double()


def windows(n, start_every=16):
    starts = list(range(0, n - WINDOW, start_every))
    return [(max(0, s - WARMUP), s, s + WINDOW) for s in starts]


def train_and_predict(cc, x_all, tip_all, train_mask, hidden, seed):
    with torch.no_grad():
        feats = cc.encoder(x_all)
    torch.manual_seed(seed)
    model = SeqResidual(cc, feats[train_mask], hidden)
    wins = [w for w in windows(len(x_all)) if train_mask[w[1] : w[2]].any()]
    length = WARMUP + WINDOW
    idx = torch.stack([torch.arange(e - length, e).clamp_min(0) for _, _, e in wins])  # (W, L)
    loss_mask = torch.zeros_like(idx, dtype=torch.bool)
    for i, (_, s, e) in enumerate(wins):
        loss_mask[i, length - (e - s) :] = train_mask[s:e]
    fw, tw = feats[idx], tip_all[idx]
    params = [p for n_, p in model.named_parameters() if not n_.startswith("cc.")]
    opt = torch.optim.Adam(params, lr=LR)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, STEPS)
    for _ in range(STEPS):
        opt.zero_grad()
        err = (model(fw) - tw).pow(2).sum(-1)
        loss = err[loss_mask].mean() / 1e-6
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        return model(feats.unsqueeze(0))[0]


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    x_tr, tip_tr, fam = d.x_tr, d.tip_tr, d.fam
    hidden = int(sys.argv[1])
    seeds = [int(s) for s in sys.argv[2].split(",")]
    mode = sys.argv[3] if len(sys.argv) > 3 else "CV"
    t0 = time.time()
    if mode == "VAL":
        x_va, tip_va = val_data()
        x_all, tip_all = torch.cat([x_tr, x_va]), torch.cat([tip_tr, tip_va])
        tr = torch.arange(len(x_all)) < len(x_tr)
        cc = fit(x_tr, tip_tr)
        res = [rmse(train_and_predict(cc, x_all, tip_all, tr, hidden, s)[~tr], tip_va) for s in seeds]
        print(
            json.dumps(
                {
                    "hidden": hidden,
                    "VAL": [round(r, 3) for r in res],
                    "val_mean": round(float(np.mean(res)), 3),
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )
    else:
        folds = {}
        for f in FOLDS:
            tr = torch.from_numpy(fam != f)
            cc = fit(x_tr[tr], tip_tr[tr])
            folds[f] = float(
                np.mean([rmse(train_and_predict(cc, x_tr, tip_tr, tr, hidden, s)[~tr], tip_tr[~tr]) for s in seeds])
            )
        print(
            json.dumps(
                {
                    "hidden": hidden,
                    "cv": round(float(np.mean(list(folds.values()))), 3),
                    "folds": {k: round(v, 2) for k, v in folds.items()},
                    "s": round(time.time() - t0, 1),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
