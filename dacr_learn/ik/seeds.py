"""IK starts from a bank of poses: the admissible samples whose tips lie nearest each target.

A uniform random start is often far from any solution (a whole-body model has many variables over large ranges: an
arm's joints span several radians), and Levenberg–Marquardt then needs many iterations or a restart. A
:class:`PoseBank` samples the admissible set once (uniformly, :meth:`~dacr_learn.ik.Limits.sample`), keeps the
tip poses of the samples, and for each target returns the K samples of nearest tip pose as the solver's seeds
(``solve_ik(..., seeds=bank.seeds(target, K))``). The distance is Euclidean in
(w·p/L, R flattened): ‖Δp‖·w/L and ‖ΔR‖_F (= 2√2·sin(angle/2)) weigh alike, L the model's length, w
:data:`POSITION_WEIGHT`; position-only targets use the position alone. On the Panda + 3-segment robot this
cuts the LM iterations per solution about threefold (docs/arm.md), on the 3-segment robot alone about twofold
(``IKOptions(bank=...)``, docs/ik.md). Works for any SolverModel.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import F64
from .adapters import SolverModel

POSITION_WEIGHT = 10.0   # a position difference of L/10 weighs like a rotation of about 40°
CHUNK = 64               # targets per distance block: its CHUNK × size floats stay in cache for the top-k


class PoseBank:
    """``size`` admissible samples of ``model`` (seeded: reproducible) and their tip poses.

    :meth:`seeds` (B, K, D): per target the K samples of nearest tip (distinct samples, nearest first).
    """

    def __init__(self, model: SolverModel, size: int = 8192, seed: int = 0):
        if size < 1:
            raise ValueError(f"size: expected >= 1 samples, got {size}")
        self.model, self.size = model, size
        gen = torch.Generator().manual_seed(seed)
        self.x = model.limits.sample(size, gen)
        parts = [model.tip_and_jacobian(chunk)[:2] for chunk in self.x.split(4096)]
        self.position = torch.cat([p for p, _ in parts]).to(F64)
        self.rotation = None if parts[0][1] is None else torch.cat([r for _, r in parts]).to(F64)
        self._weight = POSITION_WEIGHT / model.length
        self._bank: dict[bool, tuple[Tensor, Tensor]] = {}   # the samples' features (F, size) float32 and their
                                                              # squared norms, with and without the rotation

    def _features(self, position: Tensor, rotation: Tensor | None) -> Tensor:
        scaled = position * self._weight
        return scaled if rotation is None else torch.cat([scaled, rotation.flatten(-2)], dim=-1)

    def seeds(self, target: Tensor, count: int) -> Tensor:
        """Seeds (B, count, D) for targets (B, 4, 4) poses or (B, 3) positions [m] in the model's base frame."""
        if count < 1 or count > self.size:
            raise ValueError(f"count: expected 1 … {self.size} seeds per target, got {count}")
        target = target.to(F64)
        pose = target.dim() == 3
        position = target[:, :3, 3] if pose else target
        use_rotation = pose and self.rotation is not None
        if use_rotation not in self._bank:
            bank = self._features(self.position, self.rotation if use_rotation else None).float()
            self._bank[use_rotation] = bank.T.contiguous(), (bank * bank).sum(-1)
        bank, norm2 = self._bank[use_rotation]
        feat = self._features(position, target[:, :3, :3] if use_rotation else None).float()
        out = []
        for rows in range(0, target.shape[0], CHUNK):      # float32 ‖b‖² − 2a·b: ranks as the distances, float64's
            block = torch.addmm(norm2, feat[rows:rows + CHUNK], bank, alpha=-2)
            out.append(block.topk(count, dim=1, largest=False).indices)
        return self.x[torch.cat(out)]
