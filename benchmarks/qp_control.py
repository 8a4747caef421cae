"""Benchmark: one constrained (QP) control step at batch 1, the current implementation side by side with the
previous one (the QP modules at ``--previous``, a git commit) and today's resolved-rate step.

The scenes of examples/qp_reach_behind_obstacle.py (the 3-segment TDCR beside a sphere, configs/scenes/
reach_tdcr3.yaml; the Panda holding it through a port above a wall, a sphere behind it, reach_panda_port.yaml), at
a state ``--warm`` steps along the example's path (the body within the dampers' influence distance, so damper
rows are in the program), with the example's target and feedforward. One thread, float64. Rows (joints to joints
unless said):

- ``today``: :class:`ResolvedRateController` with the closed-form CC Jacobian (robot) / :class:`WholeBodyController`;
- ``qp_eager_previous`` / ``qp_eager``: the QP step in eager torch (previous: NumPy program; now: torch rows);
- ``program_previous`` / ``program``: the step with the model's evaluation cached (``sense=`` returning it): the
  program built (previous: NumPy per sample; now: torch rows, eager) and solved (DAQP through its own API);
- ``solve_daqp``: DAQP alone on this step's program (:func:`solve_program`), the floor of every row;
- ``qp_exported_previous`` (with ``--aoti``, where runs/qp_previous_<scene>.pt2 exists or with ``--aoti-previous``):
  the previous exported path, its evaluation (``Sensing``) as an AOTInductor package called through the package's
  Python wrapper, the program in NumPy;
- ``qp_exported`` (with ``--aoti``): :class:`~dacr_learn.deploy.qp_export.ExportedStep`, the step up to the solve
  as one package (:func:`export_step`), then DAQP and the joints; ``step_program_exported``: its package call alone.

Every row is asserted to give the same step (≤ 1e-9 m/rad per joint, the solver's tolerance) as the previous eager
step before it is timed. Packages: runs/qp_step_<scene>.pt2 (now) and runs/qp_previous_<scene>.pt2, built when
missing or without ``--reuse`` (minutes each). Candidates run interleaved (benchmarks/timing.py), so load slows
them alike; eager rows (milliseconds) run ``--eager-rounds`` rounds, the fast rows ``--rounds`` rounds of 10 calls.
Medians and p99 of the wall time, and the median CPU time of this process [µs].

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/qp_control.py [--aoti robot|all] [--reuse] [--json]
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(ROOT / "benchmarks"))
import qp_reach_behind_obstacle as example  # noqa: E402
from timing import time_interleaved  # noqa: E402

from dacr_learn.deploy.qp_control import solve_program  # noqa: E402
from dacr_learn.deploy.qp_export import ExportedStep, export_step  # noqa: E402

F64 = torch.float64
TARGET_US = 400.0
SAME_STEP = 1e-9                    # [m, rad] per joint: the solver's tolerance on these scaled steps
PREVIOUS = "8713ff7"                # the QP modules before the program moved into torch


def previous_modules(commit: str) -> dict[str, types.ModuleType]:
    """The QP control modules (deploy.qp_control, arm.qp_control) as they were at ``commit`` (``git show``),
    imported beside today's (the rest of the package is today's)."""
    out = {}
    for key, path in (("deploy", "dacr_learn/deploy/qp_control.py"), ("arm", "dacr_learn/arm/qp_control.py")):
        source = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:{path}"], capture_output=True, text=True,
                                check=True).stdout
        name = f"dacr_learn.{key}.qp_control_previous"
        source = source.replace("from ..deploy.qp_control import", "from ..deploy.qp_control_previous import")
        module = types.ModuleType(name)
        module.__package__, module.__file__ = f"dacr_learn.{key}", f"{commit}:{path}"
        sys.modules[name] = module
        exec(compile(source, module.__file__, "exec"), module.__dict__)
        out[key] = module
    return out


def previous_controller(modules: dict, name: str, qp, setup: dict, ex):
    """The previous implementation's controller with the same model, config, scene (and port, dt)."""
    if name == "robot":
        return modules["deploy"].QPController(setup["model"], qp.config, scene=setup["scene"],
                                              points_per_segment=qp.points_per_segment)
    return modules["arm"].WholeBodyQPController(setup["model"], qp.config, setup["port"], dt=ex.dt,
                                                scene=setup["scene"], points_per_segment=qp.points_per_segment)


def timed(fns: dict, rounds: int, calls: int) -> dict[str, dict[str, float]]:
    """Candidates interleaved (:func:`timing.time_interleaved`): wall p50 and p99 and CPU p50 [µs], calls."""
    cpu: dict[str, list[int]] = {k: [] for k in fns}

    def with_cpu(name: str, fn):
        def call():
            c = time.process_time_ns()
            fn()
            cpu[name].append(time.process_time_ns() - c)
        return call
    wall = time_interleaved({k: with_cpu(k, f) for k, f in fns.items()}, rounds, calls, round_seconds=0.5)
    return {k: {"p50": 1e6 * float(np.median(wall[k])), "p99": 1e6 * float(np.percentile(wall[k], 99)),
                "cpu": float(np.median(cpu[k])) / 1e3, "calls": len(wall[k])} for k in fns}


def warm_state(controller, q0: torch.Tensor, path: torch.Tensor, steps: int) -> torch.Tensor:
    q = q0[None]
    for i in range(steps):
        q = controller.step(q, path[i:i + 1], path[i + 1:i + 2] - path[i:i + 1])
    return q


def build(package: Path, reuse: bool, make) -> float | None:
    """Build a package with ``make(package)`` unless ``reuse`` and it exists; the build's seconds, or None."""
    if reuse and package.exists():
        return None
    t = time.perf_counter()
    make(package)
    return time.perf_counter() - t


def candidates(setup: dict, today, qp, previous, modules, q, target, ff, args, name: str) -> dict:
    """Every row of one scene, checked to give the previous step, then timed (module docstring)."""
    x = setup["model"].variables(q)
    reference = previous.step(q, target, ff)
    sensed, sensed_previous = qp.sense(x), previous.sense(x)
    out: dict = {"dampers_in_program": int((sensed.distance[0] < qp.config.influence).sum()), "deviation": {}}
    cached, cached_previous = copy.copy(qp), copy.copy(previous)
    cached.custom_sense, cached_previous.custom_sense = (lambda _: sensed), (lambda _: sensed_previous)
    qp.step(q, target, ff)
    program = qp.solved[0][0]
    eager = {"today": lambda: today.step(q, target, ff), "qp_eager_previous": lambda: previous.step(q, target, ff),
             "qp_eager": lambda: qp.step(q, target, ff)}
    fast = {"program_previous": lambda: cached_previous.step(q, target, ff),
            "program": lambda: cached.step(q, target, ff),
            "solve_daqp": lambda: solve_program(program, "daqp")}
    if args.aoti in ("all", name):
        runs = ROOT / "runs"
        package = runs / f"qp_step_{name}.pt2"
        out["aoti_build_s"] = build(package, args.reuse, lambda p: export_step(qp, p, q, target, ff))
        exported = ExportedStep(qp, package)
        fast |= {"qp_exported": lambda: exported.step(q, target, ff),
                 "step_program_exported": lambda: exported.loader.run([q, target, ff])}
        old_package = runs / f"qp_previous_{name}.pt2"
        if args.aoti_previous or old_package.exists():
            out["aoti_build_previous_s"] = build(old_package, args.reuse, lambda p: (
                torch._inductor.aoti_compile_and_package(torch.export.export(modules["deploy"].Sensing(previous),
                                                                             (x,)), package_path=str(p))))
            exported_previous = copy.copy(previous)
            exported_previous.custom_sense = torch._inductor.aoti_load_package(str(old_package))
            fast["qp_exported_previous"] = lambda: exported_previous.step(q, target, ff)
    for key, fn in (eager | fast).items():
        if key not in ("today", "solve_daqp", "step_program_exported"):
            out["deviation"][key] = dev = float((fn() - reference).abs().max())
            assert dev <= SAME_STEP, f"{name}/{key}: the step differs from the previous one by {dev:.1e}"
    return out | timed(eager, args.eager_rounds, 10) | timed(fast, args.rounds, 10)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=100, help="interleaved rounds of 10 calls of each fast row")
    p.add_argument("--eager-rounds", type=int, default=10, help="interleaved rounds of the eager rows (>= 20 calls)")
    p.add_argument("--warm", type=int, default=120, help="steps along the example's path before timing")
    p.add_argument("--aoti", choices=("none", "robot", "all"), default="none")
    p.add_argument("--reuse", action="store_true", help="load runs/qp_step_<scene>.pt2, runs/qp_previous_<scene>.pt2 "
                                                        "where they exist (no rebuild)")
    p.add_argument("--aoti-previous", action="store_true", help="also build runs/qp_previous_<scene>.pt2 (without "
                                                                "it: that row only where the package exists)")
    p.add_argument("--previous", default=PREVIOUS, help="git commit of the previous QP modules")
    p.add_argument("--points", type=int, default=8, help="body points per segment the QP sees")
    p.add_argument("--scenes", default="robot,arm")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    ex = example.parse_args(["--points", str(args.points)])
    modules = previous_modules(args.previous)
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "previous": args.previous,
              "load_average_before": " ".join(f"{v:.2f}" for v in os.getloadavg())}
    for name, make, compared in (("robot", example.robot_setup, ("resolved_rate", "qp")),
                                 ("arm", example.arm_setup, ("whole_body", "whole_body_qp"))):
        if name not in args.scenes.split(","):
            continue
        setup = make(ex)
        today, qp = (setup["controllers"][k] for k in compared)
        previous = previous_controller(modules, name, qp, setup, ex)
        path, w = setup["path"], args.warm
        q = warm_state(qp, setup["q0"], path, w)
        target, ff = path[w:w + 1], path[w + 1:w + 2] - path[w:w + 1]
        report[name] = candidates(setup, today, qp, previous, modules, q, target, ff, args, name)
    report["load_average_after"] = " ".join(f"{v:.2f}" for v in os.getloadavg())
    if args.json:
        print(json.dumps(report, indent=2))
        return report
    print(f"one control step, batch 1, 1 thread, {args.points} body points per segment, {report['date']} "
          f"(load {report['load_average_before']} → {report['load_average_after']}); wall p50 / p99, CPU p50 [µs]")
    for name in ("robot", "arm"):
        if name not in report:
            continue
        r = report[name]
        worst = max(r["deviation"].values())
        print(f"  {name}: {r['dampers_in_program']} damper rows; every row's step within {worst:.1e} of the previous "
              f"step" + (f"; AOTI build {r['aoti_build_s'] or 0:.0f} s (0: reused)" if "aoti_build_s" in r else ""))
        for key, row in r.items():
            if isinstance(row, dict) and "p50" in row:
                print(f"    {key:>24} {row['p50']:>10.0f} {row['p99']:>10.0f} {row['cpu']:>10.0f}"
                      f"   ({row['calls']} calls)")
    print(f"  target: qp step <= {TARGET_US:.0f} µs p50")
    return report


if __name__ == "__main__":
    main()
