"""IK refinement for a controller, every tick: a fixed number of Levenberg–Marquardt iterations from a warm start,
branch-free, so it exports with torch.export and AOTInductor like the other inference modules.

:class:`IKRefinement`: (target (B, 4, 4) [m] — or (B, 3) with ``position_only`` —, q0 (B, N) [m, rad]) →
(q (B, N), pos_err (B,) [m], rot_err (B,) [rad]). Each iteration is :func:`~.refine.limited_step` on every row (the
limits inside the step) with the trial kept where it lowers the cost (``torch.where``: no data-dependent control
flow), λ adapted per row as in :class:`~.refine.Refinement`. With the previous tick's solution as q0 a few
iterations reach micrometres (docs/ik.md); far from a solution use :func:`~.solver.solve_ik`.

    python -m dacr_learn.ik.exported --robot configs/robots/tdcr_3seg_coupled.yaml --out exports/ik_tdcr3
    refine = dacr_learn.load_exported("exports/ik_tdcr3", "refine")
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ...checks import F64
from ...deploy.export import FORMAT, MAX_BATCH, file_sha256, output_folder, write_export
from ...lie import pose_from_parts
from ...robot import RobotSpec
from ..adapters import ConstantCurvature
from ..refine import fused_matmul, lm_iteration, residual, spd_solve_unrolled


class IKRefinement(nn.Module):
    """Fixed-iteration IK refinement on the analytic CC model of a robot (module docstring), float64.

    Its AOTInductor package (:func:`~dacr_learn.deploy.export.write_module`) writes the small matrix products inline
    and every concatenation as a pointwise kernel: no BLAS call and no aliased view of a concatenated buffer, each of
    which the runtime wraps in a heap-allocated tensor handle per call (C++, 3 iterations: 1,496 → 518
    ``operator new`` and 122 → 68 µs per call side by side under load; the package builds ~2× longer, its kernels are
    larger)."""

    inline_products = True
    inductor_configs = {"force_pointwise_cat": True}

    def __init__(self, spec: RobotSpec, iterations: int = 3, position_only: bool = False, damping: float = 1e-6):
        super().__init__()
        if iterations < 1:
            raise ValueError(f"iterations: expected >= 1, got {iterations}")
        if not damping > 0:
            raise ValueError(f"damping: expected > 0, got {damping}")
        self.model = ConstantCurvature(spec)
        self.fold, self.decoder = self.model.space.fold, self.model.space.decoder    # submodules: their buffers
        self.iterations, self.position_only, self.damping = iterations, position_only, damping
        self.num_joints = spec.num_joints

    def forward(self, target: Tensor, q0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        position = target if self.position_only else target[:, :3, 3]
        rotation = None if self.position_only else target[:, :3, :3]
        x = self.model.limits.project(self.model.variables(q0))
        r, jac, pos_err, rot_err = residual(self.model, x, position, rotation, fused_matmul)
        cost = (r * r).sum(-1)
        state = x, r, jac, cost, torch.full_like(cost, self.damping), pos_err, rot_err
        for _ in range(self.iterations):                  # every row takes the projector: no data-dependent step
            state = lm_iteration(self.model, state, position, rotation, spd_solve_unrolled, fused_matmul, False)
        x, _, _, _, _, pos_err, rot_err = state
        return self.model.joints(x), pos_err, rot_err


def export_refinement(robot: str | Path | RobotSpec, out: str | Path, *, iterations: int = 3,
                      position_only: bool = False, aoti: bool = True) -> dict[str, Any]:
    """Export :class:`IKRefinement` of a robot as the module ``refine`` (``refine.pt2`` [and ``refine.aoti.pt2``]) into
    ``out``, verified against the eager module on 64 warm-started targets; returns the metadata. Load it with
    ``dacr_learn.load_exported(out, "refine")``."""
    spec = RobotSpec.coerce(robot)
    module = IKRefinement(spec, iterations, position_only).eval()
    out = output_folder(out)
    g = torch.Generator().manual_seed(0)
    x = module.model.limits.sample(64, g)
    pos, rot, _ = module.model.tip_and_jacobian(x)
    q0 = module.model.joints(module.model.limits.project(x + 0.02 * module.model.limits.scale * torch.randn(
        x.shape, generator=g, dtype=F64)))
    target = pos if position_only else pose_from_parts(rot, pos)
    target_shape = [3] if position_only else [4, 4]
    source = {"path": str(robot), "sha256": file_sha256(robot)} if isinstance(robot, (str, Path)) else None
    meta = {"format": FORMAT, "task": "ik_refinement", "dtype": "float64", "torch_version": torch.__version__,
            "max_batch": MAX_BATCH, "aoti_autotune": False, "source_robot": source, "robot": spec.to_dict(),
            "features": "clarke", "iterations": iterations, "position_only": position_only,
            "modules": {"refine": {"inputs": [["target", target_shape], ["q0", [spec.num_joints]]],
                                   "outputs": [["q", [spec.num_joints]], ["pos_err", []], ["rot_err", []]]}}}
    return write_export(out, meta, {"refine": module}, {"refine": (target, q0)}, {"refine": module}, aoti=aoti,
                        autotune=False, against="the eager refinement")

