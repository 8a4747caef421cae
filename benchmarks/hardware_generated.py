"""Latency of a saved hardware model's FK: the hand-folded module against the generated one, side by side.

For each ``--ckpt`` (python -m dacr_learn.hardware --save): the folded FK of ``dacr_learn.export``
(:mod:`dacr_learn.hardware.deploy.inference` or :mod:`~dacr_learn.hardware.deploy.compositional_inference`)
and :class:`generated_fk.GeneratedHardwareFK` (the eager model's code, traced), both
float32, torch.export'ed and compiled with AOTInductor, timed interleaved in this process (one thread unless
``--threads``) at each ``--batches`` size on the checkpoint's example commands (and play states of a history
model); p50 and p95 per call [µs] and their ratio, and the largest |exported − eager| of each package against
its module run eagerly in float64 (the generated one: the eager model's numerics).

    .venv/bin/python benchmarks/hardware_generated.py --ckpt /tmp/fold_v4_model/model.pt /tmp/fold_v6_model/model.pt
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from generated_fk import GeneratedHardwareFK  # noqa: E402
from timing import time_interleaved  # noqa: E402

from dacr_learn import export as dexport  # noqa: E402
from dacr_learn.console import quiet_third_party_warnings, run_cli  # noqa: E402
from dacr_learn.hardware.deploy.checkpoint import load_hardware_model  # noqa: E402
from dacr_learn.hardware.deploy.export import modules  # noqa: E402


def inputs(model, fk, batch: int) -> tuple[torch.Tensor, ...]:
    """Example commands (batch, S) [mm] float32, repeated to ``batch`` rows, and their own play states."""
    servo = model.examples.float()
    servo = servo.repeat(batch // servo.shape[0] + 1, 1)[:batch].contiguous()
    return (servo, fk.initial_state(servo).contiguous()) if model.history else (servo,)


def measure(ckpt: Path, out: Path, batches: list[int], rounds: int, calls: int) -> dict:
    model = load_hardware_model(ckpt)
    built = {"folded": modules(model, torch.float32)["fk"], "generated": GeneratedHardwareFK(model).eval()}
    reference = {"folded": modules(model, torch.float64)["fk"], "generated": GeneratedHardwareFK(model, torch.float64)}
    packages, deviation = {}, {}
    for name, module in built.items():
        files = dexport.write_module(name, module, inputs(model, module, 2), out, aoti=True)
        packages[name] = torch._inductor.aoti_load_package(str(out / files["aoti"]))
        x = inputs(model, module, model.examples.shape[0])
        with torch.no_grad():
            got, want = packages[name](*x), reference[name](*(v.double() for v in x))
        deviation[name] = max((g.double() - w).abs().max().item() for g, w in zip(got, want, strict=True))
    rows = {}
    for batch in batches:
        x = inputs(model, built["folded"], batch)
        fns = {name: (lambda p=p, x=x: p(*x)) for name, p in packages.items()}
        with torch.inference_mode():
            seconds = time_interleaved(fns, rounds, max(1, calls // batch), warmup=20)
        us = {k: v * 1e6 for k, v in seconds.items()}
        rows[batch] = {k: {f"p{q}_us": round(float(np.percentile(v, q)), 1) for q in (50, 95)} for k, v in us.items()}
        rows[batch]["ratio_p50"] = round(rows[batch]["generated"]["p50_us"] / rows[batch]["folded"]["p50_us"], 2)
    return {"model": model.name, "history": model.history, "members": len(model.members),
            "max_abs_deviation": deviation, "batches": rows}


def table(results: dict) -> str:
    lines = [f"{'model':<28} {'batch':>5} {'folded p50/p95 µs':>20} {'generated p50/p95 µs':>22} {'ratio p50':>10}"]
    for r in results.values():
        for batch, row in r["batches"].items():
            f, g = row["folded"], row["generated"]
            lines.append(f"{r['model']:<28} {batch:>5} {f['p50_us']:>10.1f} /{f['p95_us']:>8.1f} "
                         f"{g['p50_us']:>12.1f} /{g['p95_us']:>8.1f} {row['ratio_p50']:>10.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", type=Path, nargs="+", required=True, help="saved hardware models")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 256])
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--calls", type=int, default=2560, help="calls per round at batch 1 (÷ batch at larger ones)")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    if min(args.batches) < 1 or args.rounds < 1 or args.calls < 1 or args.threads < 1:
        p.error("--batches, --rounds, --calls and --threads must be ≥ 1")
    torch.set_num_threads(args.threads)
    quiet_third_party_warnings()
    with tempfile.TemporaryDirectory() as tmp:
        results = {}
        for i, ckpt in enumerate(args.ckpt):
            (Path(tmp) / str(i)).mkdir()
            results[str(ckpt)] = measure(ckpt, Path(tmp) / str(i), args.batches, args.rounds, args.calls)
    report = {"benchmark": "hardware_generated", "threads": torch.get_num_threads(), "torch": torch.__version__,
              "results": results}
    print(table(results))
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    sys.exit(run_cli(main))
