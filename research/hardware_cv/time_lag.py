"""A first-order lag (viscoelastic creep) of the commands, exp(-dt/tau) with the recorded
timestamps, fed to the static CC model (refitted). Prints one JSON line per tau.

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `time_lag.py`). ~30 s.
Run from the repository root: python -m research.hardware_cv.time_lag
"""
import json
import math

import torch

from .common import cv_static_cc, setup


def lowpass(x, tau, stamps):
    if tau == 0:
        return x
    out, state = torch.empty_like(x), x[0].clone()
    out[0] = state
    for t in range(1, x.shape[0]):
        a = math.exp(-float(stamps[t] - stamps[t - 1]) / tau)
        state = a * state + (1 - a) * x[t]
        out[t] = state
    return out


def main() -> None:
    torch.set_num_threads(1)
    stamps = torch.as_tensor(setup().train_rec.timestamp, dtype=torch.float64)
    for tau in (0, 0.1, 0.2, 0.4, 0.8):
        print(json.dumps({"tau_s": tau, **cv_static_cc(lambda x, tau=tau: lowpass(x, tau, stamps))}), flush=True)


if __name__ == "__main__":
    main()
