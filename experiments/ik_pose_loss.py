"""Exploration behind the IK pose loss (docs/ablation.md, "Multi-segment IK with a pose loss").

    .venv/bin/python experiments/ik_pose_loss.py --steps 2000 --n-train 100000 --variants all

Trains the IK of the 3-segment coupled robot with each loss variant through the ablation runner's
``fit`` (fixed steps, batch 256, MLP 4x64, seed 0) and prints, on the ablation's fixed clean test set:
the mean position / rotation error of the analytic FK of the predicted joints, the joint error against
the sampled joints, the constraint residual and the fraction of predictions outside the joint limits
(a bend angle above the segment's limit or a length outside its range). "ramp": ``pose_ramp``, the
feature loss moved linearly to the pose loss over that fraction of the steps; "anchor": the feature
weight kept beside the pose loss after the ramp.
"""
from __future__ import annotations

import argparse

import torch

from dacr_learn.ablation import runner
from dacr_learn.robot import RobotSpec

ROBOT = "configs/robots/tdcr_3seg_coupled.yaml"
CONDITIONS = {"joint_noise": 2e-4, "offset": 1e-3, "pose_noise_pos": 5e-4, "pose_noise_rot": 8.7e-3}
RAMP = {"feature_weight": 0.0, "pose_weight": 1.0, "rot_weight": 0.1, "pose_ramp": 0.3}
VARIANTS = {   # name: (features, IKModule loss settings)
    "clarke_feature": ("clarke", {}),
    "raw_feature": ("raw", {}),
    "clarke_pose": ("clarke", {"feature_weight": 0.0, "pose_weight": 1.0}),
    "raw_pose": ("raw", {"feature_weight": 0.0, "pose_weight": 1.0}),
    "clarke_pose_rot0.1": ("clarke", {"feature_weight": 0.0, "pose_weight": 1.0, "rot_weight": 0.1}),
    "clarke_ramp0.3_rot0.1": ("clarke", RAMP),
    "clarke_ramp0.3_rot0.1_anchor1e-4": ("clarke", {**RAMP, "feature_weight": 1e-4}),
    "raw_ramp0.3_rot0.1_anchor1e-4": ("raw", {**RAMP, "feature_weight": 1e-4}),
    "clarke_ramp0.3_rot1_anchor1e-4": ("clarke", {**RAMP, "feature_weight": 1e-4, "rot_weight": 1.0}),
    "clarke_ramp0.6_rot0.1_anchor1e-4": ("clarke", {**RAMP, "feature_weight": 1e-4, "pose_ramp": 0.6}),
    "clarke_ramp0.3_rot0.1_anchor1e-3": ("clarke", {**RAMP, "feature_weight": 1e-3}),
    "clarke_ramp0.3_rot0.1_anchor1e-2": ("clarke", {**RAMP, "feature_weight": 1e-2}),
    "raw_ramp0.3_rot0.1_anchor1e-3": ("raw", {**RAMP, "feature_weight": 1e-3}),
    "clarke_ramp0.05_rot0.1": ("clarke", {**RAMP, "pose_ramp": 0.05}),
    "raw_ramp0.05_rot0.1": ("raw", {**RAMP, "pose_ramp": 0.05}),
}


@torch.no_grad()
def out_of_limits(spec: RobotSpec, features: torch.Tensor) -> float:
    """Fraction of feature tensors (N, m, 4) with a segment beyond its bend or length limits."""
    bad = torch.zeros(features.shape[0], dtype=torch.bool)
    for k, seg in enumerate(spec.segments):
        phi = features[:, k, :2].norm(dim=-1) / seg.radius
        lo, hi = seg.length_range or (seg.length, seg.length)
        bad |= (phi > seg.bend * 1.001) | (features[:, k, 2] < lo - 1e-5) | (features[:, k, 2] > hi + 1e-5)
    return bad.float().mean().item()


def run(name: str, steps: int, n_train: int) -> str:
    features, loss = VARIANTS[name]
    cfg = {"robots": {"tdcr3": ROBOT}, "model": {"width": 64, "depth": 4, "activation": "silu", "lr": 3e-3, **loss},
           "train": {"steps": steps, "batch_size": 256}, "test": {"n": 5000, "seed": 1000003},
           "conditions": CONDITIONS}
    spec = RobotSpec.from_yaml(runner.resolve_path(ROBOT))
    module, seconds = runner.fit(cfg, runner.Job("tdcr3", "ik", features, n_train, 0), spec)
    test = runner.test_set(cfg, spec, "clean")
    s = runner.evaluate(module, "ik", test)
    limits = out_of_limits(spec, module.model.encoder(module.model(test["pose"])))
    return (f"{name:34s} steps={steps} n_train={n_train} pos={s['pos_err_mean_mm']:.3f} mm "
            f"rot={s['rot_err_mean_deg']:.3f} deg joint={s['joint_err_mean_mm']:.2f} mm "
            f"residual={s['constraint_residual_max_m']:.1e} m out_of_limits={limits:.3f} fit={seconds:.0f} s")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--n-train", type=int, default=100_000)
    p.add_argument("--variants", nargs="+", default=["all"], help=f"'all' or some of {list(VARIANTS)}")
    args = p.parse_args()
    torch.set_num_threads(1)
    for name in VARIANTS if args.variants == ["all"] else args.variants:
        print(run(name, args.steps, args.n_train), flush=True)


if __name__ == "__main__":
    main()
