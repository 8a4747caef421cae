"""Tendon-space friction as a play (backlash) on each command, width constant or growing with
the tendon's wrap angle / pull, fed to the static CC model (refitted). Prints one JSON line per
configuration. Usage: python experiments/hardware_cv/tendon_play.py"""
import json

from common import bend_angles, cv_static_cc, fit, passes, tendon_play, tip_tr, x_tr

cc0 = fit(x_tr, tip_tr)
wrap = bend_angles(cc0, x_tr) @ passes.T          # (n, N) total bend angle along each tendon's path
pull = x_tr.clamp_min(0)                          # (n, N) pulled amount (a tension proxy)
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
