"""Diagnosis (issue 22): which segment's transform is wrong in a trained compositional model. Numbers:
docs/history/compositional.md, "Twisting segments: the roll (2026-11-26)" (the user's command on hetero_4seg_types).

    .venv/bin/python -m research.twist_head.segment_errors RUN_DIR [RUN_DIR ...]

For 10 000 fresh samples (seed 10 000) of the run's robot: per segment k, the error of the learned T_k
(base of k → its end) against the CC model's, position in mm and % of l_k, rotation in degrees; and the error
of every segment end frame in the base frame (the last is the tip).
"""
import sys

import torch

from dacr_learn import load_model
from dacr_learn.data import generate
from dacr_learn.kinematics import segment_poses, segment_tip_poses
from dacr_learn.metrics import pose_errors


def report(run: str) -> None:
    model = load_model(run, torch.float64).eval()
    spec = model.spec
    data = generate(spec, 10_000, seed=10_000, dtype=torch.float64)
    with torch.no_grad():
        own, ends = model.segment_transforms(data["q"]), model.segment_ends(data["q"])
    true_own, true_ends = segment_poses(spec, data["features"]), segment_tip_poses(spec, data["features"])
    print(f"{run} ({spec.name}, rolled segments {model.roll.tolist()})")
    for k, seg in enumerate(spec.segments):
        e, f = pose_errors(own[:, k], true_own[:, k]), pose_errors(ends[:, k], true_ends[:, k])
        print(f"  segment {k} type {seg.type:3s}: own T_k {e['pos_err'].mean() * 1e3:.4f} mm "
              f"({100 * e['pos_err'].mean() / seg.length:.4f} % of l_k), {torch.rad2deg(e['rot_err']).mean():.4f}°; "
              f"end frame {f['pos_err'].mean() * 1e3:.4f} mm, {torch.rad2deg(f['rot_err']).mean():.4f}°")
    tip = pose_errors(ends[:, -1], true_ends[:, -1])
    print(f"  tip: {100 * tip['pos_err'].mean() / spec.total_length:.4f} % of length, "
          f"{torch.rad2deg(tip['rot_err']).mean():.4f}°")


def main() -> None:
    for run in sys.argv[1:]:
        report(run)


if __name__ == "__main__":
    main()
