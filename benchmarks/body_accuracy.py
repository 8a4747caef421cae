"""Body accuracy of the learned models against the data's true body (docs/body.md).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/body_accuracy.py [--json out.json] [--scale 1.0]
    .venv/bin/python benchmarks/body_accuracy.py --ckpt runs/NAME/version_0/last.ckpt [--source cosserat]

Each row trains one model with ``training.FKModule`` (a small budget: ``--scale`` multiplies the sample counts)
and compares its body (:mod:`dacr_learn.body`) with the true body of held-out samples at every body point:

- ``compositional_cc``: the compositional model (twist head, strain units) of the 3-segment coupled robot trained on
  CC data with the tip loss only; true body: the exact CC arcs. Target: ≤ 0.05 % of the length at every point.
- ``fk_shape_cc``: a monolithic FK network with a shape output (``body_points`` 8, ``body_weight`` 1), CC data.
- ``fk_shape_cosserat``: the shape output on Cosserat data (the robot lying horizontal, gravity along −x) as offsets
  from the CC arcs (``body_prior`` "cc"); ``fk_shape_cosserat_no_prior`` the points themselves; ``compositional_
  cosserat`` the compositional model (context "distal") with the body loss on its twist arcs. True body: the rod's
  nodes. Baseline: the CC arcs of the same joints. Target: ≥ 5× closer than them.

Error of a point: ‖p̂ − p‖ [m]. Reported in % of the robot's length: ``worst_point`` = the largest over the body
points of the mean over the held-out samples (the target's measure), ``tip`` the same at the last point,
``sample_mean`` / ``sample_p95`` = mean and 95th percentile over samples of each sample's worst point.
``--ckpt`` measures a trained FK run instead (its robot; fresh held-out samples of ``--source``, seed 12345).
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
import warnings
from pathlib import Path

import lightning.pytorch as pl
import torch

from dacr_learn import load_model
from dacr_learn.body import cc_body
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

ROOT = Path(__file__).resolve().parents[1]
CC_ROBOT = "configs/robots/tdcr_3seg_coupled.yaml"
COSSERAT_ROBOT = "configs/robots/tdcr_3seg_cosserat.yaml"
COSSERAT = {"steps_per_segment": 8}          # the rod's nodes: 8 per segment, the points of the body
POINTS = 8                                   # body points per segment
ROWS = {   # name: (robot, source, n_train, epochs, batch, FKModule arguments)
    "compositional_cc": (CC_ROBOT, "cc", 20_000, 60, 128, dict(
        structure="compositional", width=64, depth=3, lr=0.01, rotation="twist", rot_weight=0.1)),
    "fk_shape_cc": (CC_ROBOT, "cc", 20_000, 20, 128, dict(
        width=128, depth=3, lr=0.003, rotation="6d", rot_weight=0.1, body_points=POINTS, body_weight=1.0)),
    "fk_shape_cosserat": (COSSERAT_ROBOT, "cosserat", 5_000, 30, 128, dict(
        width=128, depth=3, lr=0.003, rotation="6d", rot_weight=0.1, body_points=POINTS, body_prior="cc",
        body_weight=1.0)),
    "fk_shape_cosserat_no_prior": (COSSERAT_ROBOT, "cosserat", 5_000, 30, 128, dict(
        width=128, depth=3, lr=0.003, rotation="6d", rot_weight=0.1, body_points=POINTS, body_weight=1.0)),
    "compositional_cosserat": (COSSERAT_ROBOT, "cosserat", 5_000, 30, 128, dict(
        structure="compositional", context="distal", width=64, depth=3, lr=0.01, rotation="twist", rot_weight=0.1,
        body_weight=1.0)),
}
N_TEST = 1_000


def errors(pred: torch.Tensor, true: torch.Tensor, length: float) -> dict[str, float]:
    """Summary [% of length] of point errors between bodies (B, P, 3) (see the module docstring)."""
    e = (pred - true).norm(dim=-1) / length * 100
    worst = e.amax(-1)
    return {"worst_point": e.mean(0).max().item(), "tip": e[:, -1].mean().item(), "sample_mean": worst.mean().item(),
            "sample_p95": worst.quantile(0.95).item()}


def datamodule(robot: str, source: str, n_train: int, batch: int, seed: int = 0,
               cache: Path | None = None) -> KinematicsDataModule:
    extra = {"source": "cosserat", "cosserat": COSSERAT} if source == "cosserat" else {}
    if cache is not None and source == "cosserat":
        extra["cache_dir"] = str(cache / f"cosserat_{n_train}_{seed}")
    dm = KinematicsDataModule(str(ROOT / robot), n_train=n_train, n_val=200, n_test=N_TEST, batch_size=batch,
                              seed=seed, body_points=POINTS, **extra)
    dm.setup()
    return dm


def measure(model: torch.nn.Module, test: dict[str, torch.Tensor], spec: RobotSpec, source: str) -> dict[str, float]:
    """The model's body against the split's true body, and (Cosserat) the CC arcs of the same joints against it."""
    model = model.double().eval()
    q, true = test["q"].double(), test["backbone"].double()
    with torch.no_grad():
        out = errors(model.body(q, POINTS).points, true, spec.total_length)
    if source == "cosserat":               # the CC arcs of the same joints are the baseline
        cc = errors(cc_body(spec, test["features"].double(), POINTS).points, true, spec.total_length)
        out.update({f"cc_{k}": v for k, v in cc.items()}, ratio=cc["worst_point"] / out["worst_point"])
    return out


def run_row(name: str, scale: float, cache: Path | None) -> dict:
    robot, source, n_train, epochs, batch, kwargs = ROWS[name]
    start = time.perf_counter()
    dm = datamodule(robot, source, max(1, round(scale * n_train)), batch, cache=cache)
    generated = time.perf_counter() - start
    pl.seed_everything(0, verbose=False)
    module = FKModule(str(ROOT / robot), **kwargs)
    trainer = pl.Trainer(max_epochs=epochs, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                         check_val_every_n_epoch=10**6)
    trainer.fit(module, dm)
    row = {"row": name, "n_train": dm.sizes[0], "epochs": epochs, "data_s": round(generated, 1),
           "train_s": round(time.perf_counter() - start - generated, 1)}
    return row | measure(module.model, dm.splits["test"], dm.spec, source)


def run_checkpoint(ckpt: str, source: str) -> dict:
    model = load_model(ckpt, torch.float64)
    dm = KinematicsDataModule(model.spec.to_dict(), n_train=1, n_val=1, n_test=N_TEST, seed=12345, source=source,
                              cosserat=COSSERAT if source == "cosserat" else None, body_points=POINTS)
    dm.setup()
    return {"row": str(ckpt), "source": source} | measure(model, dm.splits["test"], dm.spec, source)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", nargs="+", choices=sorted(ROWS), default=list(ROWS))
    parser.add_argument("--scale", type=float, default=1.0, help="multiplies every row's training samples")
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder keeping the Cosserat datasets between runs (default: a temporary one)")
    parser.add_argument("--ckpt", default=None, help="measure this trained FK run instead of training")
    parser.add_argument("--source", choices=("cc", "cosserat"), default="cc", help="data of --ckpt's held-out set")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", module="lightning")
    logging.getLogger("lightning.pytorch").setLevel(logging.ERROR)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:        # the Cosserat rows share one dataset
        for name in [None] if args.ckpt else args.rows:
            row = run_checkpoint(args.ckpt, args.source) if args.ckpt else run_row(name, args.scale,
                                                                                    args.cache or Path(tmp))
            rows.append(row)
            print(json.dumps({k: round(v, 5) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
