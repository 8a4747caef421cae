"""Benchmark: one constrained (QP) control step at batch 1, side by side with the previous implementation and
today's resolved-rate step.

The scenes of examples/qp_reach_behind_obstacle.py (the 3-segment TDCR beside a sphere, configs/scenes/
reach_tdcr3.yaml; the Panda holding it through a port above a wall, a sphere behind it, reach_panda_port.yaml), at
a state ``--warm`` steps along the example's path (the body within the dampers' influence distance, so clearance
rows are in the program). One thread, float64. Rows:

- ``today``: :class:`ResolvedRateController` with the closed-form CC Jacobian (robot) / :class:`WholeBodyController`;
- ``qp_previous``: the previous QP step: clearances with Jacobians by central differences of the whole body
  (2D + 1 body evaluations, as the released example's provider did) and DAQP through qpsolvers;
- ``qp_eager``: :class:`QPController` / :class:`WholeBodyQPController` with ``scene=``: one closed-form
  evaluation of tip, body and their Jacobians, the scene's distance gradients, DAQP through its own API;
- ``program_daqp`` / ``program_qpsolvers_daqp`` / ``program_proxqp``: the step with its evaluation cached (the
  program in NumPy and its solution): DAQP directly, through qpsolvers, proxqp through qpsolvers (if installed);
- ``sensing_aoti`` / ``qp_aoti`` (with ``--aoti``): the evaluation (:class:`Sensing`: tip, Jacobian, clearances
  and their Jacobians) as an AOTInductor package (minutes to build; ``--reuse`` loads runs/qp_<scene>.pt2), alone
  and driving the QP step (``qp_aoti``: joints to joints; ``qp_aoti_variables``: in the IK variables,
  :meth:`~QPController.step_variables`, for a loop that keeps its state in them).

Candidates run interleaved (benchmarks/timing.py), so load slows them alike; eager rows (milliseconds) run
``--eager-rounds`` rounds, the fast rows ``--rounds`` rounds of 10 calls (≥ 1,000 calls each by default). Medians
and p99 of the wall time, and the median CPU time of this process (less sensitive to a shared machine) [µs].

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/qp_control.py [--aoti robot|all] [--reuse] [--json]
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import qpsolvers
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(ROOT / "benchmarks"))
import qp_reach_behind_obstacle as example  # noqa: E402
from timing import time_interleaved  # noqa: E402

from dacr_learn.deploy.qp_control import Sensing  # noqa: E402

F64 = torch.float64
TARGET_US = 400.0


class CentralDifferences:
    """The previous clearance provider: d (B, P·O) of the body's points (``per_segment`` per segment) to the
    scene and ∂d/∂x by central differences of the whole body (2D + 1 evaluations, steps 1e-5 of each scale)."""

    def __init__(self, model, scene, per_segment: int):
        self.model, self.scene, self.k = model, scene, per_segment
        self.steps = 1e-5 * model.limits.scale.to(F64)

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, dim = x.shape
        shift = torch.diag(self.steps)
        probe = torch.cat([x.unsqueeze(1), x.unsqueeze(1) + shift, x.unsqueeze(1) - shift], dim=1)
        body = self.model.body(probe.reshape(-1, dim), self.k)
        d = (self.scene.distances(body.points)[0] - body.radius[:, None]).unflatten(0, (b, 2 * dim + 1)).flatten(2)
        return d[:, 0], ((d[:, 1:dim + 1] - d[:, dim + 1:]) / (2 * self.steps[:, None])).transpose(1, 2)


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
        q = controller.step(q, path[i:i + 1])
    return q


def candidates(setup: dict, today, qp, q: torch.Tensor, target: torch.Tensor, args, name: str) -> dict:
    """Every row of one scene, timed (module docstring)."""
    model = setup["model"]
    x = model.variables(q)
    sensed = qp.sense(x)
    out: dict = {"dampers_in_program": int((sensed.distance[0] < qp.config.influence).sum())}
    previous = copy.copy(qp)
    previous.scene, previous.distances = None, CentralDifferences(model, setup["scene"], qp.points_per_segment)
    previous.config = dataclasses.replace(qp.config, direct=False)
    out["previous_max_deviation"] = float((previous.step(q, target) - qp.step(q, target)).abs().max())
    eager = {"today": lambda: today.step(q, target), "qp_previous": lambda: previous.step(q, target),
             "qp_eager": lambda: qp.step(q, target)}
    fast = {}
    for key, solver, direct in (("program_daqp", "daqp", True), ("program_qpsolvers_daqp", "daqp", False),
                                ("program_proxqp", "proxqp", False)):
        if solver in qpsolvers.available_solvers:
            cached = copy.copy(qp)
            cached.config = dataclasses.replace(qp.config, solver=solver, direct=direct)
            cached.custom_sense = lambda _: sensed
            fast[key] = lambda c=cached: c.step(q, target)
    package = ROOT / "runs" / f"qp_{name}.pt2"
    if args.aoti in ("all", name) and not (args.reuse and package.exists()):
        package.parent.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        try:
            program = torch.export.export(Sensing(qp), (x,))
            torch._inductor.aoti_compile_and_package(program, package_path=str(package))
            out["aoti_build_s"] = time.perf_counter() - t
        except Exception as err:                                 # report the failure, time the other rows
            out["aoti_error"] = f"{type(err).__name__}: {str(err)[:300]}"
            package.unlink(missing_ok=True)
    if args.aoti in ("all", name) and package.exists():
        compiled = copy.copy(qp)
        compiled.custom_sense = torch._inductor.aoti_load_package(str(package))
        out["aoti_max_deviation"] = float((compiled.step(q, target) - qp.step(q, target)).abs().max())
        fast["sensing_aoti"] = lambda: compiled.custom_sense(x)
        fast["qp_aoti"] = lambda: compiled.step(q, target)
        fast["qp_aoti_variables"] = lambda: compiled.step_variables(x, target)
    return out | timed(eager, args.eager_rounds, 10) | timed(fast, args.rounds, 10)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=100, help="interleaved rounds of 10 calls of each fast row")
    p.add_argument("--eager-rounds", type=int, default=10, help="interleaved rounds of the eager rows (>= 20 calls)")
    p.add_argument("--warm", type=int, default=120, help="steps along the example's path before timing")
    p.add_argument("--aoti", choices=("none", "robot", "all"), default="none")
    p.add_argument("--reuse", action="store_true", help="load runs/qp_<scene>.pt2 where it exists (no rebuild)")
    p.add_argument("--points", type=int, default=8, help="body points per segment the QP sees")
    p.add_argument("--scenes", default="robot,arm")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    ex = example.parse_args(["--points", str(args.points)])
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "load_average_before": " ".join(f"{v:.2f}" for v in os.getloadavg())}
    for name, build, compared in (("robot", example.robot_setup, ("resolved_rate", "qp")),
                                  ("arm", example.arm_setup, ("whole_body", "whole_body_qp"))):
        if name not in args.scenes.split(","):
            continue
        setup = build(ex)
        today, qp = (setup["controllers"][k] for k in compared)
        q = warm_state(qp, setup["q0"], setup["path"], args.warm)
        report[name] = candidates(setup, today, qp, q, setup["path"][args.warm:args.warm + 1], args, name)
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
        print(f"  {name}: {r['dampers_in_program']} damper rows; previous vs new step deviation "
              f"{r['previous_max_deviation']:.1e}" + (f"; AOTI build {r.get('aoti_build_s', 0):.0f} s (0: reused), "
                                                       f"deviation {r['aoti_max_deviation']:.1e}"
                                                       if "aoti_max_deviation" in r else ""))
        for key, row in r.items():
            if isinstance(row, dict):
                print(f"    {key:>24} {row['p50']:>10.0f} {row['p99']:>10.0f} {row['cpu']:>10.0f}"
                      f"   ({row['calls']} calls)")
    print(f"  target: qp step <= {TARGET_US:.0f} µs p50 (robot alone)")
    return report


if __name__ == "__main__":
    main()
