"""Follow-the-leader side by side: dacr_learn.plan against the sampling-based FTL planner of the Continuum Robotics
Laboratory (RSS 2026; its source in ../shared/reference/sb-ftl-cr-planner), same robot, same curves, same metric.

    python benchmarks/ftl.py [--per-class 40] [--library 10000] [--skip-peer]

1. the peer runs in its own virtual environment (.bench/ftl_peer_venv, made here with ``python -m venv`` and
   ``pip install numpy scipy scikit-learn tqdm matplotlib`` on first use) through benchmarks/ftl_peer.py: it draws
   the curves with its generators (quadratic Bézier, S, C; per class --per-class curves), builds its library once
   and plans each curve from its 10 waypoints (40 interpolation steps between them);
2. dacr_learn.plan plans each curve from the dense version of the same curve (1,001 points), the robot
   configs/robots/ftl_3seg_unit.yaml on configs/arms/free_base.urdf (an ideal 6-DoF base, as the peer's);
3. both plans are scored by dacr_learn.plan.metric against the dense curve, steps with s ≤ min(curve length, L)
   (the peer's tip position gives its s, by projection onto the curve; its Clarke coordinates and base pose give
   its backbone through the same body code). The peer is also scored against its own 10-waypoint polyline.

Prints a Markdown table; writes results.json beside the peer's files (--out, default .bench/ftl). Timing: wall
clock, the peer's library counted once.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import venv
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dacr_learn.arm import Composite, load_arm  # noqa: E402
from dacr_learn.plan import Path as Polyline  # noqa: E402
from dacr_learn.plan import plan_ftl, shape_deviation  # noqa: E402
from dacr_learn.plan.body import body  # noqa: E402

PEER = ROOT.parent / "shared" / "reference" / "sb-ftl-cr-planner"
BENCH = ROOT / ".bench"
VENV = BENCH / "ftl_peer_venv"
PACKAGES = ["numpy", "scipy", "scikit-learn", "tqdm", "matplotlib"]
F64 = torch.float64


def peer_python() -> Path:
    python = VENV / "bin" / "python"
    if not python.exists():
        print(f"making {VENV} (pip install {' '.join(PACKAGES)})", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *PACKAGES], check=True)
    return python


def free_base_model() -> Composite:
    arm = load_arm(ROOT / "configs" / "arms" / "free_base.urdf", "tool")
    return Composite(arm, torch.eye(4, dtype=F64), ROOT / "configs" / "robots" / "ftl_3seg_unit.yaml")


def peer_variables(run: dict) -> torch.Tensor:
    """The peer's dense plan as the free base's variables: (x, y, z, yaw, pitch, roll) with R = Rz·Ry·Rx, then its
    Clarke coordinates (ρ_re, ρ_im per segment: the same coordinates with d = the tendon offset)."""
    rot, pos = run["base_orientation"], run["base_position"]
    yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    pitch = np.arcsin(np.clip(-rot[:, 2, 0], -1, 1))
    roll = np.arctan2(rot[:, 2, 1], rot[:, 2, 2])
    return torch.from_numpy(np.concatenate([pos, np.stack([yaw, pitch, roll], -1), run["clarke"]], -1))


def score(model: Composite, x: torch.Tensor, s: torch.Tensor, path: Polyline, tip_err: torch.Tensor) -> dict:
    b = body(model, x)
    mean, worst = shape_deviation(b.points, b.arc, path, s)
    length = model.robot.length
    return {"tip_max": float(tip_err.max()) / length, "dev_mean": 100 * float(mean.mean()) / length,
            "dev_max": 100 * float(worst.max()) / length, "steps": int(s.shape[0])}


def score_peer(model: Composite, run: dict, path: Polyline) -> tuple[dict, float]:
    """The peer's plan scored on ``path``: s of each step by projecting its tip; steps up to min(length, L)."""
    x = peer_variables(run)
    tip_ours = model.tip_and_jacobian(x)[0]
    fk_gap = float((tip_ours - torch.from_numpy(run["tip"])).norm(dim=-1).max())
    s, gap = path.project(tip_ours)
    keep = s <= min(path.length, model.robot.length) + 1e-9
    return score(model, x[keep], s[keep], path, gap[keep]), fk_gap


def summarise(rows: list[dict], key: str) -> dict:
    vals = [r[key] for r in rows]
    return {"dev_mean": float(np.mean([v["dev_mean"] for v in vals])),
            "dev_max": float(np.max([v["dev_max"] for v in vals])),
            "tip_max": float(np.max([v["tip_max"] for v in vals]))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--per-class", type=int, default=40)
    p.add_argument("--library", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(BENCH / "ftl"), help="folder of the run (default .bench/ftl)")
    p.add_argument("--skip-peer", action="store_true", help="reuse the peer's run already in --out")
    args = p.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load = os.getloadavg()
    if not args.skip_peer:
        t0 = time.perf_counter()
        subprocess.run([str(peer_python()), str(ROOT / "benchmarks" / "ftl_peer.py"), "--peer", str(PEER),
                        "--out", str(out), "--per-class", str(args.per_class), "--library", str(args.library),
                        "--seed", str(args.seed)], check=True, env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
        print(f"peer done in {time.perf_counter() - t0:.0f} s", flush=True)
    peer_times = json.loads((out / "peer.json").read_text())
    curves = np.load(out / "curves.npz")
    kinds = [str(k) for k in curves["kinds"]]
    model = free_base_model()
    rows = []
    for i, kind in enumerate(kinds):
        dense, sparse = Polyline(curves[f"dense_{i}"]), Polyline(curves[f"sparse_{i}"])
        t0 = time.perf_counter()
        plan = plan_ftl(model, dense)
        ours_s = time.perf_counter() - t0
        run = dict(np.load(out / f"peer_{i}.npz"))
        peer, fk_gap = score_peer(model, run, dense)
        peer_own, _ = score_peer(model, run, sparse)
        ours = score(model, plan.x, plan.s, dense, plan.tip_err)
        rows.append({"kind": kind, "ours": ours, "ours_success": plan.success, "ours_reason": plan.reason,
                     "ours_s": ours_s, "peer": peer, "peer_own": peer_own, "peer_s": peer_times["curve_s"][i],
                     "fk_gap": fk_gap})
        verdict = "ok" if plan.success else plan.reason
        print(f"{i + 1}/{len(kinds)} {kind}: ours {ours['dev_mean']:.3f} % ({ours_s:.1f} s, {verdict}), "
              f"peer {peer['dev_mean']:.3f} % ({peer_times['curve_s'][i]:.1f} s)", flush=True)
    (out / "results.json").write_text(json.dumps({"rows": rows, "peer": peer_times, "started": started,
                                                  "load": load}, indent=1))
    table(rows, peer_times, started, load)


def table(rows: list[dict], peer_times: dict, started: str, load) -> None:
    print(f"\n{started}, load average {load[0]:.1f} at the start; {len(rows)} curves; % of the robot's length L = 3\n")
    print("| class | planner | tip error max [L] | shape dev. mean [%] | shape dev. max [%] | success "
          "| time per curve, median [s] |")
    print("|---|---|---|---|---|---|---|")
    for kind in ("bezier", "s", "c", "all"):
        sel = [r for r in rows if kind in ("all", r["kind"])]
        if not sel:
            continue
        o, pe, po = summarise(sel, "ours"), summarise(sel, "peer"), summarise(sel, "peer_own")
        ok = sum(r["ours_success"] for r in sel)
        peer_ok = sum(r["peer"]["tip_max"] <= 1e-6 for r in sel)
        print(f"| {kind} | dacr_learn.plan | {o['tip_max']:.1e} | **{o['dev_mean']:.3f}** | {o['dev_max']:.2f} | "
              f"{ok}/{len(sel)} | {np.median([r['ours_s'] for r in sel]):.1f} |")
        print(f"| {kind} | peer (vs the curve) | {pe['tip_max']:.1e} | {pe['dev_mean']:.3f} | {pe['dev_max']:.2f} | "
              f"{peer_ok}/{len(sel)} tip ≤ 1e-6 L | {np.median([r['peer_s'] for r in sel]):.1f} |")
        print(f"| {kind} | peer (vs its 10 waypoints) | {po['tip_max']:.1e} | {po['dev_mean']:.3f} | "
              f"{po['dev_max']:.2f} | | |")
    ours_total = sum(r["ours_s"] for r in rows)
    peer_total = peer_times["library_s"] + sum(peer_times["curve_s"])
    print(f"\ntotal time: dacr_learn.plan {ours_total:.0f} s; peer {peer_total:.0f} s (library of "
          f"{peer_times['library']} shapes {peer_times['library_s']:.0f} s + curves "
          f"{sum(peer_times['curve_s']):.0f} s); ratio {ours_total / peer_total:.2f}. "
          f"Peer FK vs ours: {max(r['fk_gap'] for r in rows):.1e} m")


if __name__ == "__main__":
    main()
