"""Follow-the-leader side by side: dacr_learn.plan against the sampling-based FTL planner of the Continuum Robotics
Laboratory (RSS 2026; its source in ../shared/reference/sb-ftl-cr-planner), same robot, same curves, same metric.

    python benchmarks/ftl.py [--per-class 40] [--workers N] [--peer-python PATH] [--peer DIR] [--out DIR]
                             [--resume] [--library 10000] [--seed 0]

1. the curves: the peer's generators draw them (quadratic Bézier, S, C; --per-class of each) through
   benchmarks/ftl_peer.py, run by the peer's Python: --peer-python, default a virtual environment made here
   (.bench/ftl_peer_venv, ``pip install numpy scipy scikit-learn tqdm matplotlib`` on first use);
2. the peer's library (10,000 shapes, its threshold clusters) is built once for the robot and pickled; its wall
   time is counted apart and in the peer's total;
3. a pool of --workers processes takes the curves; each worker runs BOTH planners on its curve, one after the
   other, each on one thread (the peer in a subprocess loading the pickled library: its planning time is
   measured around follow_path + interpolate_mp, the load apart): the two see the same machine at the same time;
   dacr_learn.plan gets the dense curve (1,001 points), the robot configs/robots/ftl_3seg_unit.yaml on
   configs/arms/free_base.urdf (an ideal 6-DoF base, as the peer's);
4. both plans are scored by dacr_learn.plan.metric against the dense curve, steps with s ≤ min(curve length, L)
   (the peer's s: its tip projected onto the curve; its Clarke coordinates and base pose give its backbone
   through the same body code); the peer also against its own 10-waypoint polyline;
5. each curve's result is appended to DIR/results.jsonl as it comes (an interrupted run loses nothing;
   --resume continues it; the classes are interleaved, so a cut run covers each alike); at the end a Markdown table.

Packages: the main process needs numpy; the workers torch, numpy and dacr_learn's own imports (pyyaml,
pytorch-kinematics with arm-pytorch-utilities and pytorch-seed, lxml, absl-py, matplotlib, scipy); the peer's
Python numpy, scipy, scikit-learn (tqdm, matplotlib). ``--prepare`` (run with the project's Python) copies the
three pure-Python ones into .bench/pydeps, put on the path when it exists, and the peer's source into
.bench/peer: for a machine that has the others but neither these nor the peer's folder, e.g. 16 cores whose
python3 has torch, numpy, scipy, scikit-learn, pyyaml, lxml, matplotlib and absl-py:

    python benchmarks/ftl.py --workers 16 --peer-python python3 --peer .bench/peer --out OUT
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time
import venv
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
if (ROOT / ".bench" / "pydeps").is_dir():
    sys.path.append(str(ROOT / ".bench" / "pydeps"))

PEER = ROOT.parent / "shared" / "reference" / "sb-ftl-cr-planner"
BENCH = ROOT / ".bench"
VENV = BENCH / "ftl_peer_venv"
PACKAGES = ["numpy", "scipy", "scikit-learn", "tqdm", "matplotlib"]
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "PYTHONDONTWRITEBYTECODE": "1"}


def peer_python(given: str | None) -> str:
    if given:
        return given
    python = VENV / "bin" / "python"
    if not python.exists():
        print(f"making {VENV} (pip install {' '.join(PACKAGES)})", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *PACKAGES], check=True)
    return str(python)


def peer(python: str, command: str, out: Path, *extra: str) -> dict:
    """benchmarks/ftl_peer.py COMMAND in the peer's Python, one thread; its last output line as JSON (or {})."""
    done = subprocess.run([python, str(ROOT / "benchmarks" / "ftl_peer.py"), command, "--peer", os.environ["FTL_PEER"],
                           "--out", str(out), *extra], check=True, capture_output=True, text=True,
                          env={**os.environ, **ONE_THREAD} if command == "plan" else os.environ)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    return json.loads(lines[-1]) if lines else {}


# ---- the workers (torch and dacr_learn are imported here only) ----

_MODEL = None


def _model():
    global _MODEL
    if _MODEL is None:
        import torch

        from dacr_learn.arm import Composite, load_arm
        torch.set_num_threads(1)
        arm = load_arm(ROOT / "configs" / "arms" / "free_base.urdf", "tool")
        _MODEL = Composite(arm, torch.eye(4, dtype=torch.float64), ROOT / "configs" / "robots" / "ftl_3seg_unit.yaml")
    return _MODEL


def peer_variables(run: dict):
    """The peer's dense plan as the free base's variables: (x, y, z, yaw, pitch, roll) with R = Rz·Ry·Rx, then its
    Clarke coordinates (ρ_re, ρ_im per segment: the same coordinates with d = the tendon offset)."""
    import torch
    rot, pos = run["base_orientation"], run["base_position"]
    yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    pitch = np.arcsin(np.clip(-rot[:, 2, 0], -1, 1))
    roll = np.arctan2(rot[:, 2, 1], rot[:, 2, 2])
    return torch.from_numpy(np.concatenate([pos, np.stack([yaw, pitch, roll], -1), run["clarke"]], -1))


def score(model, x, s, path, tip_err) -> dict:
    from dacr_learn.plan import shape_deviation
    from dacr_learn.plan.body import body
    b = body(model, x)
    mean, worst = shape_deviation(b.points, b.arc, path, s)
    length = model.robot.length
    return {"tip_max": float(tip_err.max()) / length, "dev_mean": 100 * float(mean.mean()) / length,
            "dev_max": 100 * float(worst.max()) / length, "steps": int(s.shape[0])}


def score_peer(model, run: dict, path) -> tuple[dict, float]:
    """The peer's plan scored on ``path``: s of each step by projecting its tip; steps up to min(length, L)."""
    import torch
    x = peer_variables(run)
    tip_ours = model.tip_and_jacobian(x)[0]
    fk_gap = float((tip_ours - torch.from_numpy(run["tip"])).norm(dim=-1).max())
    s, gap = path.project(tip_ours)
    keep = s <= min(path.length, model.robot.length) + 1e-9
    return score(model, x[keep], s[keep], path, gap[keep]), fk_gap


def run_curve(i: int, kind: str, out: str, python: str) -> dict:
    """Both planners on curve i, one after the other, each on one thread: the row of results.jsonl."""
    from dacr_learn.plan import Path as Polyline
    from dacr_learn.plan import plan_ftl
    out_dir = Path(out)
    t0 = time.perf_counter()
    peer_times = peer(python, "plan", out_dir, "--curve", str(i))
    peer_wall = time.perf_counter() - t0
    model = _model()
    curves = np.load(out_dir / "curves.npz")
    dense, sparse = Polyline(curves[f"dense_{i}"]), Polyline(curves[f"sparse_{i}"])
    t0, cpu = time.perf_counter(), time.process_time()
    plan = plan_ftl(model, dense)
    ours_s, ours_cpu = time.perf_counter() - t0, time.process_time() - cpu
    run = dict(np.load(out_dir / f"peer_{i}.npz"))
    peer_scores, fk_gap = score_peer(model, run, dense)
    return {"curve": i, "kind": kind, "ours": score(model, plan.x, plan.s, dense, plan.tip_err),
            "ours_success": bool(plan.success), "ours_reason": plan.reason, "ours_s": ours_s, "ours_cpu_s": ours_cpu,
            "peer": peer_scores, "peer_own": score_peer(model, run, sparse)[0], "peer_s": peer_times["plan_s"],
            "peer_cpu_s": peer_times.get("cpu_s"), "peer_load_s": peer_times["load_s"], "peer_wall_s": peer_wall,
            "fk_gap": fk_gap}


# ---- the driver ----

PURE = ("pytorch_kinematics", "arm_pytorch_utilities", "pytorch_seed")


def prepare(peer_dir: Path) -> None:
    """.bench/pydeps (the pure-Python packages of :data:`PURE`, from this Python) and .bench/peer (the peer)."""
    target = BENCH / "pydeps"
    target.mkdir(parents=True, exist_ok=True)
    for name in PURE:
        origin = Path(importlib.util.find_spec(name).origin).parent
        shutil.copytree(origin, target / name, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(peer_dir, BENCH / "peer", dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__"))
    print(f"{target} ({', '.join(PURE)}) and {BENCH / 'peer'} ready")

def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--per-class", type=int, default=40)
    p.add_argument("--library", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1, help="processes, one curve each at a time (default 1)")
    p.add_argument("--peer-python", help="a Python with numpy, scipy and scikit-learn for the peer "
                   "(default: .bench/ftl_peer_venv, made on first use)")
    p.add_argument("--peer", default=str(PEER), help="the peer's source folder (default %(default)s)")
    p.add_argument("--out", default=str(BENCH / "ftl"), help="folder of the run (default .bench/ftl)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out (its curves, library, rows)")
    p.add_argument("--prepare", action="store_true", help="only copy .bench/pydeps and .bench/peer (see above)")
    args = p.parse_args()
    if args.prepare:
        return prepare(Path(args.peer))
    if args.workers < 1 or args.per_class < 1:
        raise SystemExit("--workers and --per-class: expected >= 1")
    os.environ.update(ONE_THREAD)                       # the workers (spawned) start with one thread each
    os.environ["FTL_PEER"] = str(Path(args.peer).resolve())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    python = peer_python(args.peer_python)
    rows_file = out / "results.jsonl"
    meta_file = out / "run.json"
    started = time.time()
    if args.resume and meta_file.exists():
        meta = json.loads(meta_file.read_text())
    else:
        rows_file.unlink(missing_ok=True)
        meta = {"started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load": os.getloadavg()[0],
                "workers": args.workers, "cpus": os.cpu_count(), "per_class": args.per_class,
                "library": args.library, "seed": args.seed}
        peer(python, "curves", out, "--per-class", str(args.per_class), "--seed", str(args.seed))
        print(f"curves drawn; building the peer's library ({args.library} shapes) ...", flush=True)
        meta["library_s"] = peer(python, "library", out, "--library", str(args.library),
                                 "--seed", str(args.seed))["library_s"]
        print(f"library built in {meta['library_s']:.1f} s", flush=True)
        meta_file.write_text(json.dumps(meta))
    kinds = [str(k) for k in np.load(out / "curves.npz")["kinds"]]
    done = {r["curve"] for r in read_rows(rows_file)}
    rank = {i: kinds[:i].count(k) for i, k in enumerate(kinds)}       # classes interleaved: a cut run covers all
    todo = sorted((i for i in range(len(kinds)) if i not in done), key=lambda i: (rank[i], i))
    print(f"{len(todo)} of {len(kinds)} curves to run on {args.workers} workers", flush=True)
    with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_curve, i, kinds[i], str(out), python): i for i in todo}
        for n, future in enumerate(as_completed(futures), 1):
            row = future.result()
            with open(rows_file, "a") as f:
                f.write(json.dumps(row) + "\n")
            verdict = "ok" if row["ours_success"] else row["ours_reason"]
            print(f"{n}/{len(todo)} curve {row['curve']} ({row['kind']}): ours {row['ours']['dev_mean']:.3f} % "
                  f"({row['ours_s']:.1f} s, {verdict}), peer {row['peer']['dev_mean']:.3f} % ({row['peer_s']:.1f} s)",
                  flush=True)
    meta["wall_s"] = meta.get("wall_s", 0.0) + time.time() - started
    meta_file.write_text(json.dumps(meta))
    table(sorted(read_rows(rows_file), key=lambda r: r["curve"]), meta)


def read_rows(file: Path) -> list[dict]:
    if not file.exists():
        return []
    rows = []
    for line in file.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:        # a line cut by an interruption: that curve runs again
            pass
    return rows


def summarise(rows: list[dict], key: str) -> dict:
    vals = [r[key] for r in rows]
    return {"dev_mean": float(np.mean([v["dev_mean"] for v in vals])),
            "dev_max": float(np.max([v["dev_max"] for v in vals])),
            "tip_max": float(np.max([v["tip_max"] for v in vals]))}


def table(rows: list[dict], meta: dict) -> None:
    print(f"\n{meta['started']}, {meta['cpus']} CPUs, {meta['workers']} workers, load average {meta['load']:.1f} "
          f"at the start; {len(rows)} curves; % of the robot's length L = 3\n")
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
    peer_total = meta["library_s"] + sum(r["peer_s"] for r in rows)
    o, pe = summarise(rows, "ours"), summarise(rows, "peer")
    load = sum(r["peer_load_s"] for r in rows)
    print(f"\ntotal time (sum over curves, one thread each): dacr_learn.plan {ours_total:.0f} s; peer "
          f"{peer_total:.0f} s (library of {meta['library']} shapes {meta['library_s']:.0f} s, built once on all cores"
          f" + curves {peer_total - meta['library_s']:.0f} s; loading its pickled library {load:.0f} s more, not "
          f"counted); ratio {ours_total / peer_total:.2f}. Mean shape deviation ratio "
          f"{o['dev_mean'] / pe['dev_mean']:.2f} (target ≤ 0.5); success {sum(r['ours_success'] for r in rows)}/"
          f"{len(rows)}; tip error max {o['tip_max']:.1e} L (target ≤ 1e-6). Peer FK vs ours: "
          f"{max(r['fk_gap'] for r in rows):.1e} m. Wall clock of the run {meta.get('wall_s', 0):.0f} s.")
    cpu = [(r["ours_cpu_s"], r["peer_cpu_s"]) for r in rows if r.get("peer_cpu_s") is not None]
    if cpu:
        print(f"CPU time per curve, median: dacr_learn.plan {np.median([c[0] for c in cpu]):.1f} s, peer "
              f"{np.median([c[1] for c in cpu]):.1f} s ({len(cpu)} curves)")
    for r in rows:
        if not r["ours_success"]:
            print(f"  curve {r['curve']} ({r['kind']}): {r['ours_reason']}")


if __name__ == "__main__":
    main()
