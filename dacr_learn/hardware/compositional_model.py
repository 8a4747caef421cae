"""Compositional hardware tip model: the calibrated CC segment transforms, each corrected by a shared network.

    T_k = T_k^CC(x_k) · exp(ξ_k^),   ξ_k = s · f_θ(z_k, c_k),   T_tip = T_1 · T_2 ⋯ T_m,
    tip = R_base · (p_tip + R_tip · d_marker) + t_base             (the CC model's calibration)

T_k^CC: :func:`~dacr_learn.kinematics.segment_poses` of the slack-aware encoder's features x_k; f_θ: the
per-segment network of :class:`dacr_learn.compositional.CompositionalFK` (context "none", "segment" or
"distal"); s = :data:`TWIST_SCALE`. Model, training and results: docs/compositional.md ("On the real robots").
``history=True`` (``cc_compositional_history``) adds segment k's play memory as an input; it cannot be saved.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..compositional import CompositionalFK
from ..kinematics import effective_features, segment_poses
from ..lie import chain_products
from .ccmodel import CalibratedCC
from .learned import LR, RESIDUAL_HIDDEN, STEPS, Split, train_full_batch

MEMORY_INPUTS = 2    # with history=True: segment k's play memory (ρ_k − play(ρ_k))/PLAY_WIDTH (as the history model)
TWIST_SCALE = 0.05   # network output 1 ↔ 0.05·L_s translation, 0.05 rad (≈ 2.9°) rotation per segment
CONTEXT, DEPTH, WEIGHT_DECAY, TORSION = "none", 2, 3.0, False   # chosen on the train-only proxies
# (docs/compositional.md, python -m research.hardware_cv.compositional_sweep)


class CCCompositionalResidual(nn.Module):
    """Tip (n, 3) [m] from a :class:`Split`: calibrated CC segment transforms × learned per-segment twists;
    :meth:`fit` standardises the features (:meth:`fit_normalization`) and trains the network."""

    def __init__(self, cc: CalibratedCC, context: str = CONTEXT, width: int = RESIDUAL_HIDDEN,
                 depth: int = DEPTH, weight_decay: float = WEIGHT_DECAY, torsion: bool = TORSION, steps: int = STEPS,
                 lr: float = LR, history: bool = False):
        super().__init__()
        self.history = bool(history)
        if weight_decay < 0 or steps < 1 or lr <= 0:
            raise ValueError(f"expected weight_decay >= 0, steps >= 1 and lr > 0, got weight_decay="
                             f"{weight_decay}, steps={steps}, lr={lr}")
        self.cc, self.spec = cc, cc.spec
        self.weight_decay, self.steps, self.lr = weight_decay, steps, lr
        self.fk = CompositionalFK(cc.spec, width=width, depth=depth, context=context, units="metric",
                                  extra_inputs=MEMORY_INPUTS if self.history else 0)   # + segment k's play memory
        for layer in (self.fk.net[-1], self.fk.skip):
            nn.init.zeros_(layer.weight)
        nn.init.zeros_(self.fk.net[-1].bias)
        mask = torch.ones(6)
        mask[5] = float(torsion)                                         # ξ = (v_x, v_y, v_z, ω_x, ω_y, ω_z)
        self.register_buffer("twist_mask", mask * TWIST_SCALE)

    def segment_features(self, split: Split) -> Tensor:
        """Per-segment features (n, m, 4) of the calibrated encoder in the network's dtype (float32 unless
        the model was cast), fixed columns at β = l, α = 0."""
        if not isinstance(split, Split):
            raise ValueError(f"split: expected a hardware Split (dacr_learn.hardware.learned), got {type(split)}")
        return effective_features(self.spec, split.features.to(self.fk.skip.weight.dtype))

    def corrections(self, split: Split) -> Tensor:
        """Learned correction exp(ξ_k^) of every segment: (n, m, 4, 4)."""
        front = self.fk.front
        z = front.with_context(front.norm(self.segment_features(split)))
        if self.history:
            z = torch.cat([z, split.memory.to(z.dtype)], -1)          # (n, m, C + 2)
        return self.fk.head((self.fk.net(z) + self.fk.skip(z)) * self.twist_mask)

    def segment_ends(self, split: Split) -> Tensor:
        """End frame of every segment in the robot base frame (n, m, 4, 4) [m]; [:, -1] is the tip."""
        cc_poses = segment_poses(self.spec, self.segment_features(split))
        return chain_products(cc_poses @ self.corrections(split))

    def forward(self, split: Split) -> Tensor:
        """Tip marker (n, 3) [m] in the motion-capture frame, float64 (kinematics in float32 like (e), unless cast)."""
        return self.cc.to_world(self.cc.marker_point(self.segment_ends(split)[:, -1])).double()

    def penalty(self) -> Tensor:
        """Sum of squared network weights (the linear layers' matrices; biases are not decayed)."""
        return sum(p.pow(2).sum() for n, p in self.fk.named_parameters() if n.endswith("weight"))

    def objective(self, train: Split) -> Tensor:
        """Mean squared tip error [mm²] + weight_decay × :meth:`penalty`."""
        return (self(train) - train.tip).pow(2).mean() / 1e-6 + self.weight_decay * self.penalty()

    def fit_normalization(self, train: Split) -> None:
        """The feature standardiser's statistics from the training split."""
        self.fk.front.norm.fit(self.segment_features(train))

    def fit(self, train: Split) -> None:
        self.cc.requires_grad_(False)
        self.fit_normalization(train)
        params = [p for n, p in self.fk.named_parameters() if not n.startswith("front.")]
        train_full_batch(params, lambda: self.objective(train), steps=self.steps, lr=self.lr)
