"""Training-loop overhead and data-generation throughput, measured side by side in one run.

    .venv/bin/python benchmarks/training.py [--steps 600] [--repeats 5] [--threads 1] [--json]

1. Per-step time of the Lightning FKModule (Trainer.fit, the default config's model and batch
   size, no validation, no checkpointing, no logger) vs a plain PyTorch loop running the same
   model, loss, optimizer, schedule and batches. Runs alternate and medians are reported; the
   target is ratio ≤ 1.5.
2. Synthetic-data generation rate (samples/s) for the 1-segment default robot, one thread;
   the target is ≥ 1 M samples/s.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import lightning.pytorch as pl
import torch

from dacr_learn.console import quiet_third_party_warnings
from dacr_learn.data import generate
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.training import FKModule

MODEL = dict(width=64, depth=4, rot_weight=0.1)          # as configs/default.yaml
ROBOT, BATCH = "configs/robots/default.yaml", 256


def lightning_run(dm: KinematicsDataModule, steps: int) -> float:
    module = FKModule(ROBOT, **MODEL)
    trainer = pl.Trainer(max_steps=steps, limit_val_batches=0, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0)
    start = time.perf_counter()
    trainer.fit(module, dm)
    return (time.perf_counter() - start) / steps


def plain_run(dm: KinematicsDataModule, steps: int) -> float:
    module = FKModule(ROBOT, **MODEL)
    train = dm.splits["train"]
    module.model.fit_normalization(train["q"], train["pose"])
    opt = torch.optim.AdamW(module.parameters(), lr=module.hparams.lr, weight_decay=0.0)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=module.hparams.lr, pct_start=0.05, total_steps=steps)
    start, done = time.perf_counter(), 0
    while done < steps:
        for batch in dm.train_dataloader():
            loss = module.loss(batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            done += 1
            if done == steps:
                break
    return (time.perf_counter() - start) / steps


def generation_rate(n: int, repeats: int) -> float:
    from dacr_learn.robot import RobotSpec

    spec = RobotSpec.from_yaml(ROBOT)
    times = []
    for seed in range(repeats):
        start = time.perf_counter()
        generate(spec, n, seed)
        times.append(time.perf_counter() - start)
    return n / statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    quiet_third_party_warnings()
    dm = KinematicsDataModule(ROBOT, n_train=50_000, n_val=10, n_test=10, batch_size=BATCH)
    dm.setup("fit")
    lightning_run(dm, 50), plain_run(dm, 50)                            # warm-up
    light, plain = [], []
    for _ in range(args.repeats):                                       # interleaved
        light.append(lightning_run(dm, args.steps))
        plain.append(plain_run(dm, args.steps))
    result = {"lightning_step_ms": statistics.median(light) * 1e3, "plain_step_ms": statistics.median(plain) * 1e3,
              "ratio": statistics.median(light) / statistics.median(plain),
              "ratio_of_medians_per_pair": statistics.median([a / b for a, b in zip(light, plain, strict=True)]),
              "generation_samples_per_s": generation_rate(1_000_000, args.repeats), "threads": args.threads}
    if args.json:
        print(json.dumps(result))
        return
    print(f"per-step time, batch {BATCH}, {args.steps} steps × {args.repeats} interleaved repeats, "
          f"{args.threads} thread(s):")
    print(f"  Lightning FKModule  {result['lightning_step_ms']:.3f} ms")
    print(f"  plain PyTorch loop  {result['plain_step_ms']:.3f} ms")
    print(f"  ratio               {result['ratio']:.2f}  (target ≤ 1.5; median of per-pair ratios "
          f"{result['ratio_of_medians_per_pair']:.2f})")
    print(f"synthetic generation (1 segment): {result['generation_samples_per_s'] / 1e6:.2f} M samples/s "
          f"(target ≥ 1 M/s)")


if __name__ == "__main__":
    main()
