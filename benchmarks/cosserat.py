"""Benchmark: static Cosserat-rod solves per second for the three-segment coupled robot.

configs/robots/tdcr_3seg_cosserat.yaml (12 tendons, coupled routing, NiTi backbone), float64,
``torch.set_num_threads(2)``. Each configuration: random tensions, uniform in [0, τ_max] N on one
antagonist-free pair of neighbouring tendons per segment (the others slack), and gravity along −x
(the robot horizontal). One timed call is ``solve_statics`` on the whole batch (default 10 000):
Newton to residual 1e-10, then the backbone frames and tendon lengths at every node. Reports the
median and best of ``--repeats`` calls in configurations per second (chunks solved in ``--threads``
threads, the default; beside it, interleaved, the same solve with its chunks one after another), the
Newton steps, the one-minute load average (the machine is shared), and the tip error of this step
count against 64 steps.

``--model CKPT``: also the learned surrogate of a ``train.py`` run on Cosserat data (an FKModule
checkpoint, e.g. of configs/fk_cosserat.yaml) on the same batch, side by side: its configurations per
second from the batch's joint vector (the unstretched tendon lengths the solve gives), in float32 and
float64, and its tip error against the solver on this batch.

    .venv/bin/python benchmarks/cosserat.py                       # batch 10 000, 8 steps per segment
    .venv/bin/python benchmarks/cosserat.py --steps 4 --json      # also one JSON line
    .venv/bin/python benchmarks/cosserat.py --model runs/fk_cosserat/version_0/checkpoints/last.ckpt
"""
from __future__ import annotations

import os

# On a shared machine a spinning OpenMP worker waits for a descheduled partner at every parallel
# region (2 threads ran 10x slower than 1 at load average 5); passive waiting avoids that. Set before
# torch loads OpenMP; an explicit OMP_WAIT_POLICY in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from dacr_learn.cosserat import solve_statics
from dacr_learn.data.cosserat import CosseratOptions, sample_tensions
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "robots" / "tdcr_3seg_cosserat.yaml"
TARGET = 1000.0   # configurations per second on 2 cores


def random_tensions(spec: RobotSpec, n: int, tau_max: float, seed: int) -> torch.Tensor:
    """(n, T) [N]: per segment two neighbouring tendons pulled (uniform in [0, τ_max]), the others slack
    (the sampler of the Cosserat datasets)."""
    return sample_tensions(spec, n, CosseratOptions(tension_max=tau_max), torch.Generator().manual_seed(seed))


def time_surrogate(checkpoint: str, q: torch.Tensor, repeats: int) -> dict:
    """Median configurations/s of the FK network of ``checkpoint`` on joint vectors q (B, T), float32 and
    float64 (no autograd), and its float32 tip poses (B, 4, 4)."""
    from dacr_learn.training import FKModule

    module = FKModule.load_from_checkpoint(checkpoint, map_location="cpu", weights_only=True).eval()
    out, pose = {}, None
    for dtype, name in ((torch.float32, "float32"), (torch.float64, "float64")):
        model, x = module.model.to(dtype), q.to(dtype)
        times = []
        with torch.inference_mode():
            model(x[:256])
            for _ in range(repeats):
                t0 = time.perf_counter()
                result = model(x)
                times.append(time.perf_counter() - t0)
        out[f"surrogate_configs_per_s_{name}"] = len(q) / statistics.median(times)
        pose = result.double() if pose is None else pose
    return {**out, "surrogate_structure": module.hparams.get("structure", "monolithic"),
            "surrogate_context": module.hparams.get("context", "none"), "surrogate_width": module.hparams.width}, pose


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, default=10_000)
    p.add_argument("--steps", type=int, default=8, help="RK4 steps per segment")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--tau-max", type=float, default=2.0, help="largest tension [N]")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", action="store_true", help="print one JSON line on stdout")
    p.add_argument("--model", help="FKModule checkpoint trained on Cosserat data: time it on the same batch")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    spec = RobotSpec.from_yaml(CONFIG)
    tension = random_tensions(spec, args.batch, args.tau_max, seed=0)
    gravity = torch.tensor([-9.81, 0.0, 0.0], dtype=torch.float64)

    def solve(t: torch.Tensor, steps: int = args.steps, workers: int | None = None):
        return solve_statics(spec, t, gravity=gravity, steps_per_segment=steps, workers=workers)

    solve(tension[:256])                                   # warm-up
    times, serial, sol = [], [], None
    for _ in range(args.repeats):                          # interleaved: both see the same machine load
        t0 = time.perf_counter()
        sol = solve(tension)
        times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        solve(tension, workers=1)
        serial.append(time.perf_counter() - t0)
    fine = solve(tension[:500], 64)
    err = (sol.tip[:500, :3, 3] - fine.tip[:, :3, 3]).norm(dim=-1).max() / spec.total_length
    deflection = sol.tip[:, :2, 3].norm(dim=-1) / spec.total_length
    result = {
        "configs_per_s_median": args.batch / statistics.median(times),
        "configs_per_s_best": args.batch / min(times),
        "serial_configs_per_s_median": args.batch / statistics.median(serial),
        "target": TARGET, "batch": args.batch, "steps_per_segment": args.steps, "threads": args.threads,
        "newton_steps_mean": float(sol.iterations.double().mean()), "newton_steps_max": int(sol.iterations.max()),
        "residual_max": float(sol.residual.max()), "tip_error_vs_64_steps_of_length": float(err),
        "tip_deflection_median_of_length": float(deflection.median()),
        "load_average_1min": os.getloadavg()[0], "cpus": os.cpu_count(), "torch": torch.__version__,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }
    print(f"Cosserat statics, {spec.name}, batch {args.batch}, {args.steps} RK4 steps/segment, "
          f"{args.threads} threads, float64", file=sys.stderr)
    print(f"  {result['configs_per_s_median']:.0f} configurations/s (median of {args.repeats}; best "
          f"{result['configs_per_s_best']:.0f}; target {TARGET:.0f}); chunks one after another "
          f"(workers=1): {result['serial_configs_per_s_median']:.0f}/s", file=sys.stderr)
    print(f"  Newton steps mean {result['newton_steps_mean']:.2f}, max {result['newton_steps_max']}; "
          f"residual max {result['residual_max']:.1e}; tip error vs 64 steps {err:.1e} of length; "
          f"median tip deflection {result['tip_deflection_median_of_length']:.2f} of length", file=sys.stderr)
    if args.model:
        stats, pose = time_surrogate(args.model, sol.tendon_rest_lengths, args.repeats)
        tip = (pose[:, :3, 3] - sol.tip[:, :3, 3]).norm(dim=-1) / spec.total_length
        result.update(stats, surrogate_tip_error_mean_of_length=float(tip.mean()),
                      surrogate_speedup_float32=stats["surrogate_configs_per_s_float32"]
                      / result["configs_per_s_median"])
        print(f"  surrogate ({stats['surrogate_structure']}, context {stats['surrogate_context']}, width "
              f"{stats['surrogate_width']}): {stats['surrogate_configs_per_s_float32']:.3g} configurations/s float32, "
              f"{stats['surrogate_configs_per_s_float64']:.3g} float64 ({result['surrogate_speedup_float32']:.0f}x the "
              f"solver); tip error mean {100 * float(tip.mean()):.3f} % of length on this batch", file=sys.stderr)
    result["load_average_1min_end"] = os.getloadavg()[0]
    print(f"  load average {result['load_average_1min']:.1f} on {result['cpus']} CPUs", file=sys.stderr)
    if args.json:
        print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
