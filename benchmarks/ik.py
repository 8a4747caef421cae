"""Benchmark of the IK solver (issue targets in docs/ik.md), side by side in one run.

For each robot, 1,000 reachable targets (the FK of features uniform inside the limits), K = 8 solutions each,
pose and position only: targets solved (at least one flagged solution), slots solved, flagged solutions that fail
the independent NumPy check (benchmarks/ik_reference.py: no shared code), targets with ≥ K/2 distinct solutions,
wall and CPU time (a process path's: of this process and its workers), verified solutions per second — for the paths
of the solver side by side (``grouped``: restarts in groups on shrinking batches, ``IKOptions(pool=0)``; ``pool``:
the working batch that stays full, the default without a scene; ``pool2``: its targets in 2 shards on parallel
threads; ``fused``: the pool with its LM iteration compiled, ``IKOptions(fused=True)`` (``fused2``: in 2 shards);
``bank``, ``fusedbank``, ``fusedbank2``: the same seeded by a pose bank, ``IKOptions(bank=8192)``; ``pool2p``,
``fused2p``, ``bank2p``, ``fusedbank2p``: 2 shards in worker processes, ``IKOptions(shards=2, processes=True)``; these
are timed after the start of the worker processes, ``pool_start_s``, and a first small solve that compiles the
iteration (in each worker process) and builds the bank, ``compile_s``). For the 3-segment robot also: the
warm-started refinement of one target per call (the controller case: eager, and exported if ``--export DIR`` holds
``refine`` from ``python -m dacr_learn.ik.exported``), the CLI end to end (a subprocess, start-up included) and
pytorch-kinematics' PseudoInverseIK on the equivalent rigid chain (5 joints per segment: rz θ, ry φ/2, prismatic
chord, ry φ/2, rz −θ — a relaxation: its solutions need not be constant-curvature shapes) on the same targets.

    .venv/bin/python benchmarks/ik.py                      # every row, 2 threads (~ minutes)
    .venv/bin/python benchmarks/ik.py --robots tdcr_3seg_coupled --skip latency cli pk --json
    .venv/bin/python benchmarks/ik.py --robots tdcr_3seg_coupled --paths pool --against ../old --rounds 3

``--against DIR`` runs the solve rows of this checkout and of another one (e.g. a checkout of the previous commit) as
subprocesses, interleaved round by round (same targets, seeds and threads), and prints the medians side by side.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ik_reference

from dacr_learn.data import sample_features
from dacr_learn.ik import ConstantCurvature, IKOptions, solve_ik
from dacr_learn.ik.exported import IKRefinement
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
ROBOTS = ["tdcr_3seg_coupled", "hetero_2seg_coupled", "hetero_3seg_coupled", "hetero_4seg_types",
          "hetero_5seg_coupled"]
F64 = torch.float64


def robot_path(name: str) -> Path:
    return ROOT / "configs" / "robots" / f"{name}.yaml"


def targets(spec: RobotSpec, n: int, seed: int) -> torch.Tensor:
    return forward_kinematics(spec, sample_features(spec, n, torch.Generator().manual_seed(seed), dtype=F64))


BANK = 8192   # samples of the pose bank of the *bank paths
PATHS = {"grouped": IKOptions(pool=0), "pool": IKOptions(), "pool2": IKOptions(shards=2),
         "fused": IKOptions(fused=True), "fused2": IKOptions(fused=True, shards=2), "bank": IKOptions(bank=BANK),
         "fusedbank": IKOptions(fused=True, bank=BANK), "fusedbank2": IKOptions(fused=True, bank=BANK, shards=2),
         "pool2p": IKOptions(shards=2, processes=True), "fused2p": IKOptions(fused=True, shards=2, processes=True),
         "bank2p": IKOptions(bank=BANK, shards=2, processes=True),
         "fusedbank2p": IKOptions(fused=True, bank=BANK, shards=2, processes=True)}


def first_use(path: str) -> bool:
    """Whether a path has one-time costs to pay before its timed rows (compilation, bank, worker processes)."""
    return PATHS[path].fused or PATHS[path].bank > 0 or PATHS[path].processes


def pool_start_time(path: str) -> float:
    """Wall time [s] of starting a process path's worker processes (0 once they run): spawned interpreters that
    import torch."""
    from dacr_learn.ik.workers import worker_pool
    t0 = time.perf_counter()
    worker_pool(PATHS[path].shards)
    return time.perf_counter() - t0


def workers_cpu(path: str) -> float:
    """CPU time [s] of a process path's worker processes so far (0 for the others)."""
    if not PATHS[path].processes:
        return 0.0
    from dacr_learn.ik.workers import process_cpu, run_in_processes
    return sum(run_in_processes(process_cpu, [None] * PATHS[path].shards, PATHS[path].shards))


def compile_time(name: str, position_only: bool, path: str) -> float:
    """Wall time [s] of a first small solve (64 × 8) of a fused or bank path: the one-time compilation of the robot's
    iteration for the task (the later rows of the process reuse it; in shards, on one thread each, torch compiles once
    more) and the build of the pose bank."""
    spec = RobotSpec.from_yaml(robot_path(name))
    poses = targets(spec, 64, 1)
    t0 = time.perf_counter()
    solve_ik(spec, poses[:, :3, 3] if position_only else poses, n_solutions=8, position_only=position_only,
             options=PATHS[path])
    return time.perf_counter() - t0


def solve_row(name: str, n: int, k: int, position_only: bool, seed: int, path: str = "pool") -> dict:
    spec = RobotSpec.from_yaml(robot_path(name))
    poses = targets(spec, n, seed)
    goal = poses[:, :3, 3] if position_only else poses
    cpu = time.process_time() + workers_cpu(path)
    wall = time.perf_counter()
    result = solve_ik(spec, goal, n_solutions=k, position_only=position_only, options=PATHS[path])
    wall, cpu = time.perf_counter() - wall, time.process_time() + workers_cpu(path) - cpu
    flagged = result.success.numpy()
    rows = np.nonzero(flagged)
    ref = ik_reference.check(robot_path(name), result.q.numpy()[rows], goal.numpy()[rows[0]])
    verified = int(ref["ok"].sum())
    return {"robot": name, "task": "position" if position_only else "pose", "path": path, "targets": n, "solutions": k,
            "targets_solved_pct": 100 * flagged.any(1).mean(), "slots_solved_pct": 100 * flagged.mean(),
            "false_success": int((~ref["ok"]).sum()), "verified": verified,
            "distinct_half_pct": 100 * float((result.distinct.sum(1) >= k / 2).double().mean()),
            "distinct_mean": float(result.distinct.sum(1).double().mean()), "wall_s": wall, "cpu_s": cpu,
            "verified_per_s": verified / wall, "iterations_mean": float(result.iterations.double().mean())}


def warm_start_latency(name: str, export: str | None, rounds: int) -> dict:
    """p50 of one warm-started refinement (batch 1): the target moved by 1 % of the joint ranges from q0."""
    spec = RobotSpec.from_yaml(robot_path(name))
    model = ConstantCurvature(spec)
    g = torch.Generator().manual_seed(3)
    x = model.limits.sample(rounds, g)
    pos, rot, _ = model.tip_and_jacobian(x)
    pose = torch.eye(4, dtype=F64).repeat(rounds, 1, 1)
    pose[:, :3, :3], pose[:, :3, 3] = rot, pos
    q0 = model.joints(model.limits.project(x + 0.01 * model.limits.scale * torch.randn(x.shape, generator=g,
                                                                                       dtype=F64)))
    out = {}
    runners = {"eager": IKRefinement(spec)}
    if export:
        from dacr_learn import load_exported
        runners["exported"] = load_exported(export, "refine")
    for label, fn in runners.items():
        times, ok = [], 0
        for i in range(rounds):
            t0 = time.perf_counter()
            q, pe, re = fn(pose[i:i + 1], q0[i:i + 1])
            times.append(time.perf_counter() - t0)
            ok += int(pe.item() <= 1e-6 and re.item() <= 1e-5)
        out[label] = {"p50_us": 1e6 * statistics.median(times[5:]), "solved_pct": 100 * ok / rounds}
    return out


def cli_time(name: str, n: int, k: int) -> float:
    spec = RobotSpec.from_yaml(robot_path(name))
    with tempfile.TemporaryDirectory() as d:
        np.save(Path(d) / "T.npy", targets(spec, n, 11).numpy())
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "dacr_learn.ik", "--robot", str(robot_path(name)), "--targets",
                        str(Path(d) / "T.npy"), "--out", str(Path(d) / "S.npz"), "--solutions", str(k)], check=True,
                       capture_output=True)
        return time.perf_counter() - t0


def pseudo_inverse_ik(name: str, n: int, k: int, seed: int) -> dict:
    """pytorch-kinematics' PseudoInverseIK on the equivalent rigid chain, K retries per target, its defaults but
    our tolerance (1 µm, 1e-5 rad) and 200 iterations."""
    import pytorch_kinematics as pk
    segs, _ = ik_reference.read_robot(robot_path(name))
    limit = '<limit lower="-100" upper="100" effort="1" velocity="1"/>'
    kinds = [("revolute", "0 0 1"), ("revolute", "0 1 0"), ("prismatic", "0 0 1"), ("revolute", "0 1 0"),
             ("revolute", "0 0 1")] * len(segs)
    links = "".join(f'<link name="l{i}"/>' for i in range(len(kinds) + 1))
    joints = "".join(f'<joint name="j{i}" type="{t}"><parent link="l{i}"/><child link="l{i + 1}"/>'
                     f'<axis xyz="{a}"/>{limit}</joint>' for i, (t, a) in enumerate(kinds))
    chain = pk.build_serial_chain_from_urdf(f'<robot name="cc">{links}{joints}</robot>', f"l{len(kinds)}").to(
        dtype=F64)
    lims = []
    for s in segs:
        lo, hi = s.length_range or (s.length, s.length)
        lims += [(-math.pi, math.pi), (0.0, s.bend / 2), (lo * math.sin(s.bend / 2) / (s.bend / 2) * 0.999, hi),
                 (0.0, s.bend / 2), (-math.pi, math.pi)]
    spec = RobotSpec.from_yaml(robot_path(name))
    poses = targets(spec, n, seed)
    ik = pk.PseudoInverseIK(chain, num_retries=k, max_iterations=200, pos_tolerance=1e-6, rot_tolerance=1e-5,
                            joint_limits=torch.tensor(lims, dtype=F64), early_stopping_any_converged=False)
    wall = time.perf_counter()
    sol = ik.solve(pk.Transform3d(matrix=poses))
    wall = time.perf_counter() - wall
    conv = sol.converged.reshape(n, k)
    return {"robot": name, "method": "pytorch_kinematics.PseudoInverseIK (rigid chain)", "wall_s": wall,
            "targets_solved_pct": 100 * float(conv.any(1).double().mean()),
            "slots_solved_pct": 100 * float(conv.double().mean()), "solutions_per_s": float(conv.sum()) / wall}


def against(args) -> dict:
    """The solve rows of this checkout and of ``args.against``, ``args.rounds`` interleaved rounds of subprocesses
    (each its own checkout's benchmarks/ik.py), medians of wall and CPU time per (checkout, robot, task, path)."""
    trees = {"this": ROOT, "other": Path(args.against).resolve()}
    runs: dict[tuple, list[dict]] = {}
    for i in range(args.rounds):
        for label, tree in (trees.items() if i % 2 == 0 else reversed(trees.items())):    # alternate the order
            cmd = [sys.executable, str(tree / "benchmarks" / "ik.py"), "--robots", *args.robots, "--paths", *args.paths,
                   "--targets", str(args.targets), "--solutions", str(args.solutions), "--threads", str(args.threads),
                   "--skip", "latency", "cli", "pk", "--json"]
            out = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)},
                                 check=True, capture_output=True, text=True).stdout
            for r in json.loads(out.strip().splitlines()[-1])["rows"]:
                runs.setdefault((label, r["robot"], r["task"], r["path"]), []).append(r)
    summary = []
    for (label, robot, task, path), rs in sorted(runs.items(), key=lambda kv: kv[0][1:] + kv[0][:1]):
        med = {k: statistics.median(r[k] for r in rs) for k in ("wall_s", "cpu_s", "verified_per_s")}
        worst = {"slots_solved_pct": min(r["slots_solved_pct"] for r in rs),
                 "false_success": max(r["false_success"] for r in rs)}
        summary.append({"checkout": label, "robot": robot, "task": task, "path": path, **med, **worst})
        print(f"{label:5s} {robot:22s} {task:8s} {path:6s} wall {med['wall_s']:.2f} s, CPU {med['cpu_s']:.2f} s, "
              f"{med['verified_per_s']:.0f} verified/s (medians of {len(rs)}); slots solved ≥ "
              f"{worst['slots_solved_pct']:.2f} %, false flags ≤ {worst['false_success']}", flush=True)
    return {"against": str(trees["other"]), "rounds": args.rounds, "summary": summary}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robots", nargs="+", default=ROBOTS)
    p.add_argument("--targets", type=int, default=1000)
    p.add_argument("--solutions", type=int, default=8)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--export", help="an export folder with the 'refine' module of tdcr_3seg_coupled")
    p.add_argument("--paths", nargs="+", default=["grouped", "pool"], choices=list(PATHS))
    p.add_argument("--skip", nargs="*", default=[], choices=["latency", "cli", "pk"])
    p.add_argument("--json", action="store_true")
    p.add_argument("--against", help="another checkout: its solve rows side by side with this one's (subprocesses)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds with --against")
    p.add_argument("--repeat", type=int, default=1, help="rounds of the solve rows in this process (paths alternate)")
    args = p.parse_args(argv)
    if args.against:
        report = against(args)
        if args.json:
            print(json.dumps(report))
        return report
    torch.set_num_threads(args.threads)
    rows, extra = [], {"compile_s": {}, "pool_start_s": {}}
    for name in args.robots:
        for position_only in (False, True):
            task = "position" if position_only else "pose"
            for path in (p for p in args.paths if first_use(p)):
                if PATHS[path].processes:
                    c = extra["pool_start_s"][f"{name} {task} {path}"] = pool_start_time(path)
                    print(f"{name:22s} {task:8s} {path:7s} worker processes start: {c:.1f} s", flush=True)
                c = extra["compile_s"][f"{name} {task} {path}"] = compile_time(name, position_only, path)
                print(f"{name:22s} {task:8s} {path:7s} first solve (compiles, bank), 64 × 8: {c:.1f} s", flush=True)
            for i in range(args.repeat):
                for path in (args.paths if i % 2 == 0 else args.paths[::-1]):        # alternate the order
                    rows.append(solve_row(name, args.targets, args.solutions, position_only, seed=7, path=path))
                    r = rows[-1]
                    print(f"{name:22s} {r['task']:8s} {path:7s} solved {r['targets_solved_pct']:6.2f} % targets, "
                          f"{r['slots_solved_pct']:6.2f} % slots, false flags {r['false_success']}, "
                          f"≥K/2 distinct {r['distinct_half_pct']:6.2f} %, {r['wall_s']:.2f} s wall "
                          f"({r['cpu_s']:.2f} s CPU), {r['verified_per_s']:.0f} verified solutions/s", flush=True)
            if args.repeat > 1:
                med = {p: statistics.median(r["verified_per_s"] for r in rows if r["robot"] == name
                                            and r["task"] == task and r["path"] == p) for p in args.paths}
                print(f"{name:22s} {task:8s} medians of {args.repeat}: " + ", ".join(
                    f"{p} {v:.0f}/s ({v / med[args.paths[0]]:.2f}×)" for p, v in med.items()), flush=True)
    if "tdcr_3seg_coupled" in args.robots:
        if "latency" not in args.skip:
            extra["warm_start"] = warm_start_latency("tdcr_3seg_coupled", args.export, 200)
            print("warm-started refinement, batch 1, 4 iterations:", extra["warm_start"], flush=True)
        if "cli" not in args.skip:
            extra["cli_s"] = cli_time("tdcr_3seg_coupled", args.targets, args.solutions)
            print(f"CLI end to end, {args.targets} × {args.solutions}: {extra['cli_s']:.1f} s", flush=True)
        if "pk" not in args.skip:
            extra["pytorch_kinematics"] = pseudo_inverse_ik("tdcr_3seg_coupled", args.targets, args.solutions, 7)
            print("PseudoInverseIK:", extra["pytorch_kinematics"], flush=True)
    report = {"rows": rows, **extra, "threads": args.threads, "torch": torch.__version__,
              "machine": platform.processor() or platform.machine()}
    if args.json:
        print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
