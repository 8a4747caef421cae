"""Benchmark: the arm + continuum robot (dacr_learn.arm) — whole-body IK, Jacobian, control — side by side.

Panda (configs/arms/panda.urdf, panda_link8, configs/arms/panda_mount.npy) + configs/robots/tdcr_3seg_coupled.yaml:

1. IK of ``--targets`` (1,000) random reachable whole-body pose targets (the tip poses of uniform admissible
   configurations), K = ``--solutions`` (8), in one call each, side by side:
   - ``bank``: ``solve_ik(model, T, K, seeds=model.seeds(T, K))`` (the pose bank's nearest samples; the bank's
     construction is inside the timing);
   - ``random``: ``solve_ik(model, T, K)`` (the solver's uniform random starts).
   Every flagged solution is re-checked with NumPy code that shares nothing with the solver
   (tests/arm_reference.py: the URDF walked in NumPy float64, the classic arc, the robot file's limits):
   success %, verified %, false flags, distinct solutions, CPU time (process_time) and wall time, verified
   solutions per second (wall and CPU).
2. Jacobian: ``--jacobian-samples`` configurations, float64: max |J − jacrev(FK)| and max |J_arm − pytorch-
   kinematics' jacobian at the tip| (targets ≤ 1e-10).
3. One whole-body control step (pose target, port, all limits), batch 1, one thread: eager p50, and with
   ``--aoti`` the exported whole-body step (:func:`dacr_learn.arm.exported.export_control_step`, minutes to build).
4. Tracking (examples/track_port.py's path): whole body vs decoupled, with ``--tracking``.

The machine may be shared: ``uptime`` is printed; compare the side-by-side rows, not absolute numbers.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/arm.py --threads 2 [--aoti] [--tracking] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))        # the independent NumPy references
sys.path.insert(0, str(ROOT / "examples"))
from arm_reference import UrdfArm, check_solution  # noqa: E402

from dacr_learn import load_exported  # noqa: E402
from dacr_learn.arm import Composite, load_arm  # noqa: E402
from dacr_learn.arm.control import Port, WholeBodyConfig, WholeBodyController  # noqa: E402
from dacr_learn.arm.exported import export_control_step  # noqa: E402
from dacr_learn.ik import solve_ik  # noqa: E402
from dacr_learn.lie import twist_jacobian  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402

URDF, TIP = ROOT / "configs" / "arms" / "panda.urdf", "panda_link8"
MOUNT = ROOT / "configs" / "arms" / "panda_mount.npy"
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
F64 = torch.float64
TARGETS = {"solved": 0.999, "jacobian": 1e-10, "solutions_per_s": 5000.0, "step_p50_us": 300.0}


def load_average() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def ik_side_by_side(model: Composite, spec: RobotSpec, mount: np.ndarray, n: int, k: int, seed: int) -> dict:
    x = model.limits.sample(n, torch.Generator().manual_seed(seed))
    target = model.pose_of_variables(x)
    runs = {"bank": lambda: solve_ik(model, target, k, seeds=model.seeds(target, k)),
            "random": lambda: solve_ik(model, target, k)}
    ref, out = UrdfArm(URDF, TIP), {}
    for name, fn in runs.items():
        model._bank = None                                   # the bank's construction counts in its timing
        cpu, wall = time.process_time(), time.perf_counter()
        result = fn()
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        verified = np.zeros(result.success.shape, dtype=bool)
        for b, j in result.success.nonzero().tolist():
            pos, rot, inside = check_solution(ref, mount, spec, result.q[b, j].numpy(), target[b].numpy())
            verified[b, j] = inside and pos <= 1e-6 and rot <= 1e-5
        flagged = result.success.numpy()
        distinct = result.distinct.sum(1).numpy()
        out[name] = {"targets": n, "solutions": k, "cpu_s": cpu, "wall_s": wall,
                     "solved_targets": float(verified.any(1).mean()), "flagged": float(flagged.mean()),
                     "verified": float(verified.mean()), "false_flags": int((flagged & ~verified).sum()),
                     "distinct_mean": float(distinct.mean()), "distinct_min": int(distinct.min()),
                     "targets_with_half_distinct": float((distinct >= k / 2).mean()),
                     "verified_per_s_wall": float(verified.sum() / wall),
                     "verified_per_cpu_s": float(verified.sum() / cpu),
                     "iterations_mean": float(result.iterations.double().mean())}
    return out


def jacobian_errors(model: Composite, n: int) -> dict:
    x = model.limits.sample(n, torch.Generator().manual_seed(7))
    position, _, jac = model.tip_and_jacobian(x)
    pose = model.pose_of_variables(x)
    dpose = torch.stack([torch.func.jacrev(lambda v: model.pose_of_variables(v[None])[0])(xi) for xi in x])
    theta = x[:, :model.num_arm]
    tip = torch.cat([position, torch.ones(n, 1, dtype=F64)], 1)[..., None]
    local = torch.linalg.inv(model.arm.tip_pose(theta)) @ tip                 # the tip in the tip link's frame
    reference = model.arm.chain.jacobian(theta, locations=local[:, :3, 0])
    return {"samples": n, "jacrev_max": float((jac - twist_jacobian(pose, dpose)).abs().max()),
            "pytorch_kinematics_max": float((jac[:, :, :model.num_arm] - reference).abs().max())}


def control_latency(model: Composite, aoti: bool, calls: int) -> dict:
    centre = model.base_pose(model.home[None])[0, :3, 3]
    config, port = WholeBodyConfig(), Port(tuple(centre.tolist()), 0.005)
    step = WholeBodyController(model, config, port).step
    gen = torch.Generator().manual_seed(3)
    x = model.limits.sample(1, gen)
    target = model.pose_of_variables(model.limits.project(x + 0.05 * model.limits.scale))
    x, ff = model.joints(x), torch.zeros(1, 6, dtype=F64)
    runners = {"eager": step}
    out = {}
    if aoti:
        t = time.perf_counter()
        export_control_step(model, ROOT / "runs" / "arm_step", config=config, port=port)
        runners["aoti"] = load_exported(ROOT / "runs" / "arm_step", "step")
        out["aoti_build_s"] = time.perf_counter() - t
        out["aoti_max_deviation"] = float((runners["aoti"](x, target, ff) - step(x, target, ff)).abs().max())
    for name, fn in runners.items():
        for _ in range(5):
            fn(x, target, ff)
        times = []
        for _ in range(calls if name == "aoti" else max(20, calls // 10)):
            t = time.perf_counter_ns()
            fn(x, target, ff)
            times.append((time.perf_counter_ns() - t) / 1e3)
        out[f"{name}_p50_us"] = statistics.median(times)
        out[f"{name}_p10_us"] = float(np.percentile(times, 10))
    return out


def tracking() -> dict:
    import track_port
    return track_port.main(["--out", str(ROOT / "runs" / "track_port")])["results"]


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--targets", type=int, default=1000)
    p.add_argument("--solutions", type=int, default=8)
    p.add_argument("--threads", type=int, default=2, help="torch threads for the IK (default 2)")
    p.add_argument("--jacobian-samples", type=int, default=100)
    p.add_argument("--calls", type=int, default=2000, help="timed control steps (a tenth of it eager)")
    p.add_argument("--aoti", action="store_true", help="also build and time the AOTInductor control step")
    p.add_argument("--tracking", action="store_true", help="also run examples/track_port.py")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    mount = np.load(MOUNT)
    spec = RobotSpec.from_yaml(ROBOT)
    model = Composite(load_arm(URDF, TIP), torch.from_numpy(mount), spec)
    report = {"uptime_load_before": load_average(), "threads": args.threads,
              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "")}
    torch.set_num_threads(args.threads)
    report["ik"] = ik_side_by_side(model, spec, mount, args.targets, args.solutions, args.seed)
    torch.set_num_threads(1)
    report["jacobian"] = jacobian_errors(model, args.jacobian_samples)
    report["control_step"] = control_latency(model, args.aoti, args.calls)
    if args.tracking:
        report["tracking"] = tracking()
    report["uptime_load_after"] = load_average()
    print_report(report)
    if args.json:
        print(json.dumps(report))
    return report


def print_report(r: dict) -> None:
    print(f"load (1, 5, 15 min) before {r['uptime_load_before']}, after {r['uptime_load_after']}; "
          f"IK on {r['threads']} thread(s), OMP_WAIT_POLICY={r['omp_wait_policy'] or 'unset'}")
    print(f"\nwhole-body IK, Panda + 3-segment TDCR, {r['ik']['bank']['targets']} pose targets × "
          f"{r['ik']['bank']['solutions']} solutions (1 µm, 1e-5 rad, every limit; NumPy re-check)")
    cols = ("solved_targets", "verified", "false_flags", "distinct_mean", "distinct_min", "iterations_mean",
            "cpu_s", "wall_s", "verified_per_s_wall", "verified_per_cpu_s")
    print("  " + f"{'starts':<8}" + " ".join(f"{c:>20}" for c in cols))
    for name, v in r["ik"].items():
        print("  " + f"{name:<8}" + " ".join(f"{v[c]:>20.4g}" for c in cols))
    bank = r["ik"]["bank"]
    j, c = r["jacobian"], r["control_step"]
    lines = [("targets solved (verified)", bank["solved_targets"], f">= {TARGETS['solved']}",
              bank["solved_targets"] >= TARGETS["solved"]),
             ("false success flags", bank["false_flags"], "0", bank["false_flags"] == 0),
             ("targets with >= K/2 distinct", bank["targets_with_half_distinct"], "1.0",
              bank["targets_with_half_distinct"] == 1.0),
             ("J vs jacrev (float64)", j["jacrev_max"], "<= 1e-10", j["jacrev_max"] <= TARGETS["jacobian"]),
             ("arm block vs pk jacobian", j["pytorch_kinematics_max"], "<= 1e-10",
              j["pytorch_kinematics_max"] <= TARGETS["jacobian"]),
             ("verified solutions/s (wall)", bank["verified_per_s_wall"], ">= 5000 (quiet machine)",
              bank["verified_per_s_wall"] >= TARGETS["solutions_per_s"]),
             ("control step p50 eager [µs]", c["eager_p50_us"], "<= 300", c["eager_p50_us"] <= TARGETS["step_p50_us"])]
    if "aoti_p50_us" in c:
        lines.append(("control step p50 AOTI [µs]", c["aoti_p50_us"], "<= 300",
                      c["aoti_p50_us"] <= TARGETS["step_p50_us"]))
    print("\ntargets")
    for name, value, target, ok in lines:
        print(f"  {name:<30} {value:>12.4g}  {target:<24} {'met' if ok else 'MISSED'}")
    if "aoti_build_s" in c:
        print(f"  (AOTI build {c['aoti_build_s']:.0f} s, max deviation from eager {c['aoti_max_deviation']:.1e})")
    if "tracking" in r:
        print("\ntracking (examples/track_port.py)")
        for name, v in r["tracking"].items():
            print(f"  {name:<12} position RMS {v['position_rms_mm']:.3f} mm, "
                  f"rotation RMS {v['rotation_rms_deg']:.3f}°, "
                  f"arm {v['arm_motion_rad']:.2f} rad, robot {v['robot_motion_mm']:.0f} mm, "
                  f"{v['steps_at_a_limit']} steps at a limit, {v['limit_violations']} violations, "
                  f"port {v['port_max_mm']:.3f} mm")


if __name__ == "__main__":
    main()
