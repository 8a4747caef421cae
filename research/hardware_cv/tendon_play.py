"""Tendon-space friction as a play (backlash) on each command, width constant or growing with
the tendon's wrap angle / pull, fed to the static CC model (refitted). Prints one JSON line per
configuration.

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `tendon_play.py`). ~2 min.
Run from the repository root: python -m research.hardware_cv.tendon_play
"""
import json

import torch

from .common import bend_angles, cv_static_cc, fit, setup, tendon_play


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    cc0 = fit(d.x_tr, d.tip_tr)
    wrap = bend_angles(cc0, d.x_tr) @ d.passes.T      # (n, N) total bend angle along each tendon's path
    pull = d.x_tr.clamp_min(0)                        # (n, N) pulled amount (a tension proxy)
    configs = {}
    for w0 in (0, 5e-5, 1e-4, 2e-4):
        for w1 in (0, 5e-5, 1e-4, 2e-4):
            configs[f"w0={w0 * 1e3:g}mm + {w1 * 1e3:g}mm/rad*wrap"] = w0 + w1 * wrap
    for a in (0.02, 0.05, 0.1):
        configs[f"{a:g}*pull"] = a * pull
    for a in (0.05, 0.1, 0.2):
        configs[f"{a:g}*pull*wrap"] = a * pull * wrap
    for name, w in configs.items():
        print(json.dumps({"config": name, **cv_static_cc(lambda x, w=w: tendon_play(x, w))}), flush=True)


if __name__ == "__main__":
    main()
