"""Exploration behind the IK pose loss (a frozen research script).

Numbers: docs/history/ablation.md, "Multi-segment IK with a pose loss" and its subsection "Little data: why
Clarke IK was worse at 1k, and the fix". Run from the repository root:

    python -m research.ik_pose_loss --steps 8000 --n-train 1000 --loss ramp0.05_limit1 --seeds 0 1
    python -m research.ik_pose_loss --diagnose      # why Clarke IK overfits with little data

Trains the IK of the 3-segment coupled robot, with Clarke and raw features alike, for each named loss
setting through the ablation runner's ``fit`` (fixed steps, batch 256, MLP 4x64 unless ``--set``
changes it) and prints one line per training, appended as CSV to ``--csv``: on the training samples
(``train``, at most 2 000 of them), on a validation split (2 000 fresh samples, seed 2000003: the one
used for choices) and on the ablation's fixed clean test set (``test``, reported): the mean position
[mm] / rotation [deg] error of the analytic FK of the predicted joints and the fraction of predictions
outside the joint limits (a bend angle above the segment's limit or a length outside its range), plus
the test joint error and constraint residual. "rampX": ``pose_ramp`` X (the feature loss moved linearly
to the pose loss over that fraction of the steps); "limitX": ``limit_weight`` X (joint-limit penalty);
"anchorX": a feature weight X kept beside the pose loss; "rotX": the rotation weight; "wdX": AdamW decay;
"task": ``output_scale="task"`` (network outputs scaled by their effect on the tip pose, not by their std).
"""
from __future__ import annotations

import argparse
import csv
import re
from pathlib import Path

import torch

from dacr_learn.ablation import runner
from dacr_learn.data import generate
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.models import IKModel, pose_to_vector
from dacr_learn.robot import RobotSpec
from dacr_learn.training import limit_excess

ROBOT = "configs/robots/tdcr_3seg_coupled.yaml"
CONDITIONS = {"joint_noise": 2e-4, "offset": 1e-3, "pose_noise_pos": 5e-4, "pose_noise_rot": 8.7e-3}
POSE = {"feature_weight": 0.0, "pose_weight": 1.0, "rot_weight": 0.1, "pose_ramp": 0.3}
TAGS = {"ramp": "pose_ramp", "limit": "limit_weight", "anchor": "feature_weight", "rot": "rot_weight",
        "wd": "weight_decay", "width": "width", "depth": "depth", "lr": "lr"}
VAL_SEED, VAL_N = 2000003, 2000


def loss_settings(name: str) -> dict:
    """IKModule settings of a loss name: "feature" (the feature MSE alone), or "pose" plus any of the
    ``TAGS`` (or "task") joined by "_" (e.g. "ramp0.05_limit1"): the pose loss with those settings changed."""
    if name == "feature":
        return {}
    settings = dict(POSE)
    for part in name.split("_"):
        m = re.fullmatch(r"([a-z]+)([-+0-9.e]+)", part)
        if part == "task":
            settings["output_scale"] = "task"
            continue
        if part != "pose" and (m is None or m[1] not in TAGS):
            raise ValueError(f"loss {name!r}: unknown part {part!r}, expected 'pose' or one of {sorted(TAGS)} "
                             "followed by a number")
        if m is not None:
            value = float(m[2])
            settings[TAGS[m[1]]] = int(value) if m[1] in ("width", "depth") else value
    return settings


@torch.no_grad()
def out_of_limits(spec: RobotSpec, features: torch.Tensor) -> float:
    """Fraction of feature tensors (N, m, 4) beyond the bend, length or twist limits (0.1 % slack)."""
    return (limit_excess(spec, features) > 1e-6).float().mean().item()


@torch.no_grad()
def scores(module, spec: RobotSpec, data: dict) -> tuple[float, float, float]:
    """(mean position error [mm], mean rotation error [deg], fraction out of limits) of a split."""
    s = runner.evaluate(module, "ik", data)
    return s["pos_err_mean_mm"], s["rot_err_mean_deg"], out_of_limits(spec, module.model.encoder(module.model(
        data["pose"])))


def run(features: str, loss: str, steps: int, n_train: int, seed: int) -> dict:
    settings = loss_settings(loss)
    model = {"width": 64, "depth": 4, "activation": "silu", "lr": 3e-3}
    model.update({k: settings.pop(k) for k in ("width", "depth", "lr") if k in settings})
    cfg = {"robots": {"tdcr3": ROBOT}, "model": {**model, **settings},
           "train": {"steps": steps, "batch_size": 256}, "test": {"n": 5000, "seed": 1000003},
           "conditions": CONDITIONS}
    spec = RobotSpec.from_yaml(runner.resolve_path(ROBOT))
    module, seconds = runner.fit(cfg, runner.Job("tdcr3", "ik", features, n_train, seed), spec)
    train = generate(spec, n_train, seed=1 + seed)                  # the training samples of runner.fit
    train = {k: v[:VAL_N] for k, v in train.items()}
    row = {"features": features, "loss": loss, "n_train": n_train, "seed": seed, "steps": steps}
    for split, data in (("train", train), ("val", generate(spec, VAL_N, VAL_SEED)),
                        ("test", runner.test_set(cfg, spec, "clean"))):
        names = (f"{split}_pos_mm", f"{split}_rot_deg", f"{split}_out_of_limits")
        row.update(zip(names, scores(module, spec, data), strict=True))
    s = runner.evaluate(module, "ik", runner.test_set(cfg, spec, "clean"))
    row.update(test_joint_mm=s["joint_err_mean_mm"], test_residual_m=s["constraint_residual_max_m"],
               fit_seconds=round(seconds))
    return row


@torch.no_grad()
def undetermined_share(spec: RobotSpec, features: str, n: int = 20000) -> torch.Tensor:
    """(D,) share of each standardised IK target's variance that the pose does not determine: half the mean
    squared difference to the target of the nearest pose (standardised pose_to_vector) over the variance."""
    data = generate(spec, n, seed=5, dtype=torch.float64)
    model = IKModel(spec, features, 8, 1).double()
    model.fit_normalization(data["q"], data["pose"])
    x, y = model.in_norm(pose_to_vector(data["pose"], spec.total_length)), model.out_norm(model.target(data["q"]))
    nearest = []
    for i in range(0, n, 2000):
        d = torch.cdist(x[i:i + 2000], x)
        d[torch.arange(len(d)), torch.arange(i, i + len(d))] = float("inf")
        nearest.append(d.argmin(1))
    return (y - y[torch.cat(nearest)]).square().mean(0) / 2 / y.var(0)


def tip_gain(spec: RobotSpec, features: str, n: int = 256) -> torch.Tensor:
    """(D,) median over n samples of ‖∂p/∂z_i‖ [mm]: tip displacement per unit of standardised output i."""
    data = generate(spec, 1000, seed=1, dtype=torch.float64)
    model = IKModel(spec, features, 8, 1).double()
    model.fit_normalization(data["q"], data["pose"])
    z = model.out_norm(model.target(data["q"][:n])).requires_grad_(True)
    p = forward_kinematics(spec, model.decode_features(z))[..., :3, 3] * 1e3
    jac = torch.stack([torch.autograd.grad(p[:, i].sum(), z, retain_graph=True)[0] for i in range(3)])
    return jac.norm(dim=0).median(dim=0).values


def diagnose() -> None:
    spec = RobotSpec.from_yaml(runner.resolve_path(ROBOT))
    for features in ("clarke", "raw"):
        print(f"{features}: share of target variance not determined by the pose",
              undetermined_share(spec, features).numpy().round(2))
        print(f"{features}: tip displacement per unit standardised output [mm]",
              tip_gain(spec, features).numpy().round(1))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=8000)
    p.add_argument("--n-train", type=int, nargs="+", default=[1000])
    p.add_argument("--loss", nargs="+", default=["ramp0.3"], help="loss names (see loss_settings)")
    p.add_argument("--features", nargs="+", default=["clarke", "raw"])
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--csv", type=Path, default=Path("runs/ablation_ik_tdcr3/exploration.csv"))
    p.add_argument("--diagnose", action="store_true", help="print the target ambiguity and tip gain per output")
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.diagnose:
        return diagnose()
    for loss in args.loss:
        loss_settings(loss)                                       # refuse a bad name before training
    for seed in args.seeds:
        for n in args.n_train:
            for loss in args.loss:
                for features in args.features:
                    row = run(features, loss, args.steps, n, seed)
                    print(" ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
                          flush=True)
                    new = not args.csv.is_file()
                    args.csv.parent.mkdir(parents=True, exist_ok=True)
                    with args.csv.open("a", newline="") as f:
                        w = csv.DictWriter(f, fieldnames=list(row))
                        if new:
                            w.writeheader()
                        w.writerow(row)


if __name__ == "__main__":
    main()
