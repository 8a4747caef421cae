"""Validation of IK inputs: targets and warm starts (ValueError naming what is wrong and what was expected)."""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import F64, as_floating


def pose_defects(pose: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """How far homogeneous poses (..., 4, 4) are from rigid transforms: (largest entry of |RRᵀ − I|, det R, and
    a mask of the poses that are not rigid transforms: RRᵀ = I and det R = +1 to 1e-6, last row (0, 0, 0, 1)
    to 1e-12), each (...)."""
    rot = pose[..., :3, :3]
    orth = (rot @ rot.mT - torch.eye(3, dtype=pose.dtype)).abs().amax((-2, -1))
    det = torch.linalg.det(rot)
    row = (pose[..., 3, :] - pose.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().amax(-1)
    return orth, det, (orth > 1e-6) | ((det - 1).abs() > 1e-6) | (row > 1e-12)


def check_targets(target: Tensor, position_only: bool) -> Tensor:
    """Validate IK targets: (B, 4, 4) homogeneous poses with a rotation part, or (B, 3) positions with
    ``position_only`` (a (B, 4, 4) pose is then reduced to its position). Returns float64. ValueError naming
    what is wrong: shape, non-finite entries, a rotation that is not orthonormal with det +1, a bad last row."""
    target = as_floating(target, "target").to(F64)
    shapes = "(B, 3) positions or (B, 4, 4) poses" if position_only else "(B, 4, 4) poses"
    is_pose = target.dim() == 3 and target.shape[-2:] == (4, 4)
    if not (is_pose or (position_only and target.dim() == 2 and target.shape[-1] == 3)) or target.shape[0] == 0:
        raise ValueError(f"target: expected {shapes}, got shape {tuple(target.shape)}")
    bad = ~torch.isfinite(target.flatten(1)).all(-1)
    if bad.any():
        raise ValueError(f"target: {int(bad.sum())} target(s) with NaN/inf entries, first at index "
                         f"{int(bad.nonzero()[0])}")
    if is_pose:
        orth, det, wrong = pose_defects(target)
        if wrong.any():
            i = int(wrong.nonzero()[0])
            raise ValueError(f"target: {int(wrong.sum())} pose(s) whose rotation is not a rotation matrix "
                             f"(RRᵀ = I to 1e-6, det +1) or whose last row is not (0, 0, 0, 1); first at index {i} "
                             f"(|RRᵀ − I| = {float(orth[i]):.2e}, det = {float(det[i]):.6f})")
        if position_only:
            return target[:, :3, 3]
    return target


def check_q0(q0, b: int, n: int) -> Tensor:
    q0 = as_floating(q0, "q0", "joint values").to(F64)
    if q0.dim() == 1:
        q0 = q0.expand(b, -1)
    if q0.shape != (b, n):
        raise ValueError(f"q0: expected a warm start of shape ({n},) or ({b}, {n}), got {tuple(q0.shape)}")
    if not torch.isfinite(q0).all():
        raise ValueError("q0: expected finite joint values, got NaN/inf entries")
    return q0
