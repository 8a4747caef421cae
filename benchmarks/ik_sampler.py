"""Benchmark: learned sampler seeds vs uniform random starts for the IK solver, side by side in one run.

The same targets (1,000 reachable poses of the 3-segment coupled robot: the FK of features uniform inside the
limits, a seed no training set used), K = 8 solutions each, pose and position only, three ways of starting the
solver (:func:`dacr_learn.ik.solve_ik`, the analytic CC model):

- ``random``: the solver's own uniform starts inside the limits (no seeds);
- each ``--sampler NAME=RUN``: K samples per target of a trained sampler, e.g. ``clarke`` (``features: clarke``:
  inside the limits by construction) and ``raw`` (``features: raw``: joints encoded, then projected onto the limits).

The samplers run in float32, as the IK CLI runs them; their time is part of every figure. Two settings:

1. **full solve** (the solver's defaults: restarts of stalled and duplicate starts): targets and slots solved,
   distinct solutions per target (≥ 0.5 mm apart in some joint), LM iterations per slot (all its starts), wall
   time (network part separate), distinct solutions per second of wall time (sampling included): the figure of
   merit at equal time;
2. **single shot** (``restarts=0``: every slot refines its one start, ≤ 25 iterations): how good the starts are,
   and **random at equal wall time**: random starts get as many slots as fit into the time the sampler's seeds
   plus their refinement took, and the distinct solutions found (counted up to K) are compared.

Every flagged solution is also checked by the independent NumPy checker (benchmarks/ik_reference.py). Times are
medians of ``--repeats`` interleaved runs (the order rotates); the machine load (``uptime``) is printed before and
after.

    .venv/bin/python benchmarks/ik_sampler.py --sampler clarke=runs/ik_sampler_tdcr3 \
        --sampler raw=runs/ik_sampler_tdcr3_raw --threads 1
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ik_reference

from dacr_learn import load_model
from dacr_learn.data import sample_features
from dacr_learn.ik import IKOptions, solve_ik
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.robot import RobotSpec

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def load_sampler(path: str):
    net = load_model(path)                        # float32, as the IK CLI samples
    if net.task != "sampler":
        raise ValueError(f"{path}: expected a learned sampler run (train.py fit --config "
                         f"configs/ik_sampler_tdcr3.yaml), found a {net.task} model")
    return net


def solve(spec, goal, k: int, position_only: bool, sampler, options: IKOptions, seed: int):
    """(result, network seconds, total seconds) of one solve started from the sampler's seeds or random starts."""
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    seeds = None if sampler is None else sampler.sample_features(goal, k)
    t1 = time.perf_counter()
    result = solve_ik(spec, goal, n_solutions=k, position_only=position_only, options=options, seeds=seeds)
    return result, t1 - t0, time.perf_counter() - t0


def summary(result, robot: Path, goal: torch.Tensor, k: int, net_s: float, totals: list[float]) -> dict:
    flagged = result.success.numpy()
    rows = np.nonzero(flagged)
    ref = ik_reference.check(robot, result.q.numpy()[rows], goal.numpy()[rows[0]])
    distinct = result.distinct.sum(1).clamp(max=k).double()
    return {"targets_solved_pct": 100 * flagged.any(1).mean(), "slots_solved_pct": 100 * flagged.mean(),
            "false_flags": int((~ref["ok"]).sum()), "distinct_mean": float(distinct.mean()),
            "distinct_half_pct": 100 * float((distinct >= k / 2).double().mean()),
            "iterations_mean": float(result.iterations.double().mean()), "slots": int(result.q.shape[1]),
            "network_s": net_s, "total_s": statistics.median(totals), "total_s_runs": totals,
            "distinct_per_s": float(distinct.sum()) / statistics.median(totals)}


def compare(spec, robot: Path, goal, k: int, position_only: bool, samplers: dict, options: IKOptions,
            repeats: int) -> dict[str, dict]:
    """Every method on the same targets, ``repeats`` interleaved runs each (order rotated): median times."""
    times: dict[str, list[tuple[float, float]]] = {m: [] for m in samplers}
    results = {}
    methods = list(samplers)
    for r in range(repeats):
        for m in methods[r % len(methods):] + methods[:r % len(methods)]:
            result, net_s, total_s = solve(spec, goal, k, position_only, samplers[m], options, seed=r)
            times[m].append((net_s, total_s))
            results.setdefault(m, result)
    return {m: summary(results[m], robot, goal, k, statistics.median(t[0] for t in times[m]),
                       [t[1] for t in times[m]]) for m in methods}


def equal_time_random(spec, robot: Path, goal, k: int, position_only: bool, budget_s: float, random_s: float,
                      options: IKOptions, repeats: int) -> dict:
    """Random starts given ``budget_s``: as many slots as the time of K random slots (``random_s``) scales to."""
    slots = max(k, math.floor(k * budget_s / random_s))
    runs = [solve(spec, goal, slots, position_only, None, options, seed=r) for r in range(repeats)]
    out = summary(runs[0][0], robot, goal, k, 0.0, [t for _, _, t in runs])
    out["budget_s"] = budget_s
    return out


def load_average() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def table(title: str, rows: dict[str, dict], k: int) -> str:
    lines = [f"\n{title}", "| starts | targets solved | slots solved | distinct of K | ≥ K/2 distinct | LM iter./slot "
             "| network s | total s (min–max) | distinct sol./s | false flags |", "|" + "---|" * 10]
    for name, r in rows.items():
        lines.append(f"| {name} ({r['slots']} slots) | {r['targets_solved_pct']:.2f} % | {r['slots_solved_pct']:.2f} % "
                     f"| {r['distinct_mean']:.2f} / {k} | {r['distinct_half_pct']:.1f} % | {r['iterations_mean']:.2f} "
                     f"| {r['network_s']:.2f} | {r['total_s']:.2f} ({min(r['total_s_runs']):.2f}–"
                     f"{max(r['total_s_runs']):.2f}) | {r['distinct_per_s']:.0f} | {r['false_flags']} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sampler", action="append", required=True, metavar="NAME=RUN",
                   help="a trained sampler (run folder or checkpoint) and its name in the tables; repeat for several")
    p.add_argument("--robot", default=str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"),
                   help="the samplers' robot file (read by the independent checker)")
    p.add_argument("--targets", type=int, default=1000)
    p.add_argument("--solutions", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=20261128, help="seed of the targets (no training set uses it)")
    p.add_argument("--json", help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    load_before = load_average()
    samplers = {"random": None}
    for item in args.sampler:
        name, sep, path = item.partition("=")
        if not sep or not name or not path or name in samplers:
            raise ValueError(f"--sampler {item}: expected NAME=RUN with a new name other than 'random'")
        samplers[name] = load_sampler(path)
    robot = Path(args.robot)
    spec = RobotSpec.from_yaml(robot)
    for name, net in samplers.items():
        if net is not None and net.spec != spec:
            raise ValueError(f"--sampler {name}: a sampler of robot {net.spec.name!r}, expected one of --robot {robot}")
    poses = forward_kinematics(spec, sample_features(spec, args.targets, torch.Generator().manual_seed(args.seed),
                                                     dtype=F64))
    report = {"robot": spec.name, "targets": args.targets, "solutions": args.solutions, "threads": args.threads,
              "torch": torch.__version__, "machine": platform.processor() or platform.machine(), "tasks": {}}
    k = args.solutions
    for position_only in (False, True):
        task = "position" if position_only else "pose"
        goal = poses[:, :3, 3] if position_only else poses
        full = compare(spec, robot, goal, k, position_only, samplers, IKOptions(), args.repeats)
        print(table(f"{task}, full solve (solver defaults)", full, k), flush=True)
        single = compare(spec, robot, goal, k, position_only, samplers, IKOptions(restarts=0), args.repeats)
        for name in [m for m in samplers if m != "random"]:
            single[f"random at {name}'s time"] = equal_time_random(
                spec, robot, goal, k, position_only, single[name]["total_s"], single["random"]["total_s"],
                IKOptions(restarts=0), args.repeats)
        print(table(f"{task}, single shot (restarts=0; random also at the samplers' wall time)", single, k),
              flush=True)
        report["tasks"][task] = {"full": full, "single_shot": single}
    report["load_average"] = {"before": load_before, "after": load_average()}
    print(f"\nload average (1, 5, 15 min) before: {load_before}; after: {report['load_average']['after']}; "
          f"{args.threads} torch threads, {report['machine']}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
