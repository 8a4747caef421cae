"""Exportable FK of a hardware model generated from the eager model's own code (no folded copy of its maths): the
benchmarks' counterpart of the folded :class:`dacr_learn.hardware.deploy.inference.HardwareFK`
(benchmarks/hardware_generated.py, benchmarks/latency.py).

:class:`GeneratedHardwareFK` runs :meth:`~dacr_learn.hardware.deploy.checkpoint.HardwareModel.predict` on
tensors with the same functions: the servo map, the slack-aware encoder's QP by enumeration
(:func:`enumerated_solution`, gains of :meth:`~dacr_learn.hardware.slack.SlackAwareEncoder.qp_terms` computed once),
:func:`~dacr_learn.hardware.learned.play_step` for a history model, the members' own ``forward`` on
:func:`~dacr_learn.hardware.learned.encoded_split`, and :func:`~dacr_learn.hardware.deploy.uncertainty.mean_and_sigma`;
torch.export traces it like the modules of :mod:`dacr_learn.hardware.deploy.inference`:

- servo (B, S) [mm, checkpoint column order] (+ state (B, m, 2) [m] for a history model) → tip (B, 3) [m,
  motion-capture frame] = the ensemble mean, tip_std (B, 3) [m] = the model's σ (+ the new state).
- :meth:`GeneratedHardwareFK.initial_state`: servo (B, S) → the play state (B, m, 2) [m] to start a sequence.

Float64 encoder, play and σ, members in their own dtype; ``dtype`` is that of the inputs and outputs (the
state is rounded to it between calls). The play width is :data:`~dacr_learn.hardware.learned.PLAY_WIDTH`.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from dacr_learn.checks import F64, check_tensor
from dacr_learn.hardware.deploy.checkpoint import HardwareModel
from dacr_learn.hardware.deploy.uncertainty import mean_and_sigma
from dacr_learn.hardware.learned import PLAY_WIDTH, encoded_split, play_step
from dacr_learn.hardware.slack import active_set_gains, select_active_set


def residual_maps(g: Tensor, gain: Tensor) -> Tensor:
    """(2ᴺ, N, N): I − G K_S of every set, the map x ↦ x − Gρ_S (gains K_S (2ᴺ, D, N) of
    :func:`~dacr_learn.hardware.slack.active_set_gains`)."""
    return torch.eye(g.shape[0], dtype=gain.dtype, device=gain.device) - g @ gain


def enumerated_solution(x: Tensor, sets: Tensor, gain: Tensor, residual_map: Tensor, tendon_w: Tensor) -> Tensor:
    """ρ (B, D) of x (B, N) [m] from the sets and gains of :func:`~dacr_learn.hardware.slack.active_set_gains` and their
    :func:`residual_maps` (all computed once for fixed weights): every set's residual x − Gρ_S (B, 2ᴺ, N) in
    one product, the consistent set (:func:`~dacr_learn.hardware.slack.select_active_set`), its solution ρ_S = K_S x."""
    residual = torch.einsum("sin,bn->bsi", residual_map.to(x.dtype), x)
    best = select_active_set(residual, sets, tendon_w)
    return (gain.to(x.dtype)[best] @ x.unsqueeze(-1)).squeeze(-1)


class GeneratedHardwareFK(nn.Module):
    """Servo commands (B, S) [mm] (+ play state (B, m, 2) [m]) → (tip (B, 3) [m], tip_std (B, 3) [m] (+ state))."""

    # AOTInductor options (dacr_learn.export.write_module): keep tensor constants as tensors. Inductor
    # (torch 2.13) otherwise inlines the 0-d CC parameters (tip_offset) as scalars and fails to lower
    # their reshape ("'Constant' object has no attribute 'data'").
    inductor_configs = {"always_keep_tensor_constants": True}

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.spec, self.smap, self.servo_ids = model.spec, model.smap, tuple(model.servo_ids)
        self.history, self.dtype = model.history, dtype
        self.num_servos, self.num_segments = len(self.servo_ids), model.spec.num_segments
        self.cc = model.cc
        self.members = nn.ModuleList(model.members)
        self.sigma = model.sigma_of()
        self.support = model.support if "support" in self.sigma.terms else None
        if "support" in self.sigma.terms and self.support is None:
            raise ValueError("sigma_model: its 'support' term needs the support model, which this model lacks")
        self.disagreement = "disagreement" in self.sigma.terms      # the only σ term that reads the CC tip
        with torch.no_grad():
            pretension, g, bend_w, tendon_w = model.cc.encoder.qp_terms()
            sets, gain = active_set_gains(g, bend_w, tendon_w)
        for name, value in {"pretension": pretension, "tendon_w": tendon_w, "sets": sets, "gain": gain,
                            "residual_map": residual_maps(g, gain)}.items():
            self.register_buffer(name, value.detach().contiguous(), persistent=False)

    def _check_servo(self, servo: Tensor) -> None:
        check_tensor(servo, "servo", (self.num_servos,))
        if servo.dim() != 2:
            raise ValueError(f"servo: expected shape (B, {self.num_servos}) [mm], got {tuple(servo.shape)}")

    def _check_state(self, servo: Tensor, state: Tensor | None) -> None:
        if self.history != (state is not None):
            raise ValueError(f"state: a {'history' if self.history else 'static'} model takes "
                             f"{'the play state (B, m, 2) [m]' if self.history else 'no state'}, got "
                             f"{'None' if state is None else tuple(state.shape)}")
        if state is not None:
            check_tensor(state, "state", (self.num_segments, 2))
            if state.shape[:-2] != servo.shape[:-1]:
                raise ValueError(f"state: expected shape ({servo.shape[0]}, {self.num_segments}, 2), got "
                                 f"{tuple(state.shape)}")

    def encode(self, servo: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(servo (B, S) [m], displacements x (B, N) [m], encoder features (B, m, 4)) of commands (B, S) [mm],
        float64: the servo map and the slack-aware encoder of ``HardwareModel.split``."""
        servo_m = 1e-3 * servo.to(F64)
        x = self.smap.command_displacements(self.spec, self.servo_ids, servo_m)
        rho = enumerated_solution(x + self.pretension, self.sets, self.gain, self.residual_map, self.tendon_w)
        return servo_m, x, self.cc.encoder.features_from_clarke(rho.unflatten(-1, (self.num_segments, 2)))

    def initial_state(self, servo: Tensor) -> Tensor:
        """Play state (B, m, 2) [m] to start a sequence at commands (B, S) [mm]: their own ρ (as play_operator)."""
        self._check_servo(servo)
        return self.encode(servo)[2][..., :2].to(self.dtype)

    def forward(self, servo: Tensor, state: Tensor | None = None):
        self._check_servo(servo)
        self._check_state(servo, state)
        servo_m, x, features = self.encode(servo)
        rho = features[..., :2]
        played = play_step(state.to(F64), rho, PLAY_WIDTH) if self.history else rho
        # the CC tip only where the σ reads it (its disagreement term); the checkpoints' members do not read it
        cc_tip = self.cc.tip_from_features(features) if self.disagreement else rho.new_zeros(rho.shape[0], 3)
        split = encoded_split(servo_m, x, features, played, cc_tip)
        preds = torch.stack([member(split) for member in self.members])                 # (K, B, 3)
        tip, std = mean_and_sigma(preds, split.cc_tip, rho, self.sigma, self.support)
        out = (tip.to(self.dtype), std.to(self.dtype))
        return out + (played.to(self.dtype),) if self.history else out
