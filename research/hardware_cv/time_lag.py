"""A first-order lag (viscoelastic creep) of the commands, exp(-dt/tau) with the recorded
timestamps, fed to the static CC model (refitted). Usage: python experiments/hardware_cv/time_lag.py"""
import json
import math

import torch
from common import cv_static_cc, train_rec

stamps = torch.as_tensor(train_rec.timestamp, dtype=torch.float64)


def lowpass(x, tau):
    if tau == 0:
        return x
    out, state = torch.empty_like(x), x[0].clone()
    out[0] = state
    for t in range(1, x.shape[0]):
        a = math.exp(-float(stamps[t] - stamps[t - 1]) / tau)
        state = a * state + (1 - a) * x[t]
        out[t] = state
    return out


for tau in (0, 0.1, 0.2, 0.4, 0.8):
    print(json.dumps({"tau_s": tau, **cv_static_cc(lambda x, tau=tau: lowpass(x, tau))}), flush=True)
