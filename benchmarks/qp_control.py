"""Benchmark: one constrained (QP) control step at batch 1, side by side with today's resolved-rate step.

The scenes of examples/qp_reach_behind_obstacle.py (the 3-segment TDCR beside a sphere; the Panda holding it
through a port, a sphere behind the port), at a state ``--warm`` steps along the example's path (the body within
the dampers' influence distance, so clearance rows are in the program). One thread, float64, median over
``--calls`` calls. Rows:

- ``today``: :class:`ResolvedRateController` with the closed-form CC Jacobian (robot) / :class:`WholeBodyController`
  (arm: pose-free position target, port, limits by projection);
- ``qp_eager``: :class:`QPController` / :class:`WholeBodyQPController`: model, clearances (``--points`` per segment,
  default 8; Jacobian by central differences), program and DAQP, all eager;
- ``program_daqp`` / ``program_proxqp``: the program alone (its evaluation cached): building it and solving it
  with each qpsolvers backend installed (proxqp: ``pip install proxsuite``) — the measurement behind DAQP;
- ``sensing_aoti`` / ``qp_aoti`` (with ``--aoti``): the model and clearances as an AOTInductor package
  (:class:`dacr_learn.deploy.qp_control.Sensing`; minutes to build, ``--reuse`` loads the last one) alone, and
  the QP step with it (the program in NumPy/DAQP).

Candidates run interleaved (benchmarks/timing.py), so load slows them alike.

The machine may be shared: the load average is printed; compare rows of one run, not absolute numbers.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/qp_control.py [--aoti robot|all] [--reuse] [--points 8] [--json]
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path

import qpsolvers
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(ROOT / "benchmarks"))
import qp_reach_behind_obstacle as scene  # noqa: E402
from timing import time_interleaved  # noqa: E402

from dacr_learn.deploy.qp_control import Sensing  # noqa: E402

F64 = torch.float64
TARGET_US = 400.0


def medians(fns: dict, rounds: int, calls: int) -> dict[str, dict[str, float]]:
    """Candidates run interleaved (:func:`timing.time_interleaved`): median wall time and median CPU time of this
    process per call (process_time: less sensitive to a shared machine) [µs]."""
    cpu: dict[str, list[int]] = {k: [] for k in fns}

    def with_cpu(name: str, fn):
        def call():
            c = time.process_time_ns()
            fn()
            cpu[name].append(time.process_time_ns() - c)
        return call
    wall = time_interleaved({k: with_cpu(k, f) for k, f in fns.items()}, rounds, calls, round_seconds=0.2)
    return {k: {"wall": 1e6 * float(statistics.median(wall[k])), "cpu": statistics.median(cpu[k]) / 1e3}
            for k in fns}


def cell(row: dict, key: str) -> str:
    return f"{row[key]['wall']:.0f} / {row[key]['cpu']:.0f}" if key in row else "-"


def warm_state(model, controller, q0: torch.Tensor, path: torch.Tensor, steps: int) -> torch.Tensor:
    q = q0[None]
    for i in range(steps):
        q = controller.step(q, path[i:i + 1])
    return q


def rows(model, today, qp, q: torch.Tensor, target: torch.Tensor, rounds: int, aoti: str | None, name: str) -> dict:
    """The candidates of one scene, timed interleaved; ``aoti``: "build" the Sensing package, "reuse" the one in
    runs/, or None."""
    x = model.variables(q)
    sensed = qp.sense(x)
    out: dict = {"dampers_in_program": int((sensed.distance[0] < qp.config.influence).sum())}
    fns = {"today": lambda: today.step(q, target), "qp_eager": lambda: qp.step(q, target)}
    for solver in (k for k in ("daqp", "proxqp") if k in qpsolvers.available_solvers):
        cached = copy.copy(qp)
        cached.config, cached.custom_sense = dataclasses.replace(qp.config, solver=solver), lambda _: sensed
        fns[f"program_{solver}"] = lambda c=cached: c.step_variables(x, target)
    if aoti:
        package = ROOT / "runs" / f"qp_{name}.pt2"
        if aoti == "build" or not package.exists():
            t = time.perf_counter()
            program = torch.export.export(Sensing(qp), (x,))
            torch._inductor.aoti_compile_and_package(program, package_path=str(package))
            out["aoti_build_s"] = time.perf_counter() - t
        fast = copy.copy(qp)
        fast.custom_sense = torch._inductor.aoti_load_package(str(package))
        out["aoti_max_deviation"] = float((fast.step_variables(x, target) - qp.step_variables(x, target)).abs().max())
        fns["sensing_aoti"] = lambda: fast.custom_sense(x)
        fns["qp_aoti"] = lambda: fast.step_variables(x, target)
    return out | medians(fns, rounds, 10)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=30, help="interleaved rounds of (up to) 10 calls per candidate")
    p.add_argument("--warm", type=int, default=120, help="steps along the example's path before timing")
    p.add_argument("--aoti", choices=("none", "robot", "all"), default="none")
    p.add_argument("--reuse", action="store_true", help="load runs/qp_<scene>.pt2 where it exists (no rebuild)")
    p.add_argument("--points", type=int, default=8, help="body points per segment the QP sees")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    ex = scene.parse_args(["--points", str(args.points)])
    report = {"load_average_before": " ".join(f"{v:.2f}" for v in os.getloadavg())}
    for name, build, compared in (("robot", scene.robot_setup, ("resolved_rate", "qp")),
                                  ("arm", scene.arm_setup, ("whole_body", "whole_body_qp"))):
        setup = build(ex)
        model, q0, path = setup["model"], setup["q0"], setup["path"]
        today, qp = (setup["controllers"][k] for k in compared)
        q = warm_state(model, qp, q0, path, args.warm)
        target = path[args.warm:args.warm + 1]
        aoti = ("reuse" if args.reuse else "build") if args.aoti in ("all", name) else None
        report[name] = rows(model, today, qp, q, target, args.rounds, aoti, name)
    report["load_average_after"] = " ".join(f"{v:.2f}" for v in os.getloadavg())
    if args.json:
        print(json.dumps(report, indent=2))
        return report
    print(f"one control step, batch 1, 1 thread, median wall / CPU time [µs] (load {report['load_average_before']} "
          f"→ {report['load_average_after']}; {args.points} body points per segment)")
    keys = ("today", "qp_eager", "program_daqp", "program_proxqp", "sensing_aoti", "qp_aoti")
    print("  " + f"{'scene':>8}" + "".join(f"{k:>18}" for k in keys) + f"{'dampers':>10}")
    for name in ("robot", "arm"):
        r = report[name]
        print("  " + f"{name:>8}" + "".join(f"{cell(r, k):>18}" for k in keys) + f"{r['dampers_in_program']:>10d}")
        if "aoti_max_deviation" in r:
            print(f"  ({name}: AOTI build {r.get('aoti_build_s', 0):.0f} s (0: reused), deviation from eager "
                  f"{r['aoti_max_deviation']:.1e}; target qp_aoti <= {TARGET_US:.0f} µs)")
    return report


if __name__ == "__main__":
    main()
