"""Tip models for hardware recordings: baselines, Clarke-feature networks and CC residuals.

Every model maps a :class:`Split` (one recording, with inputs precomputed by the fitted
:class:`~dacr_learn.hardware.ccmodel.CalibratedCC`) to tip positions (n, 3) [m]. The registry's models
(:mod:`.study.registry`) are described in docs/hardware.md ("The models"); history models use the command
history (rows in time order) through :func:`play_operator`.

A model is built from shapes and configuration only, then trained full batch with ``fit(train)``
(:func:`train_full_batch`), whose first step sets its data-dependent statistics (``fit_normalization``); a
checkpoint loads into a model built the same way. :func:`command_split` makes the inputs of servo commands
without a recording.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import torch
from torch import Tensor, nn

from ..layers import ClarkeDecoder
from ..models import Standardizer, mlp
from ..robot import RobotSpec
from .ccmodel import CalibratedCC
from .recording import Recording
from .servo_map import ServoMap

HIDDEN, DEPTH, STEPS, LR = 128, 2, 1500, 3e-3
PRETRAIN_SAMPLES, FINETUNE_STEPS, REHEARSAL = 4000, 500, 0.3
STEPS_ENV = "DACR_HARDWARE_STEPS"  # where set: the steps of every fit's default STEPS (quick trials, tests)
RESIDUAL_TIP_SCALE, RESIDUAL_RHO_SCALE = 5e-3, 5e-4  # [m]: output units of the residual networks
RESIDUAL_HIDDEN = 64  # the per-segment correction network sees m rows per sample
# [m] width of the Clarke-space play operator (hysteresis memory), chosen by family cross-validation on the training
# recording only (research/hardware_cv: CV 4.94 mm at 0.1 mm against 5.11 mm at 0.2 mm).
PLAY_WIDTH = 1e-4
# Input statistics of the standardised networks computed in float32, as the benchmark's scores were: in float64
# (1 ulp apart) the unstable fits move, e.g. cc_tip_residual's seed-0 v4 val RMSE 14.34 → 14.56 mm.
NORM_DTYPE = torch.float32


def play_operator(values: Tensor, width: float | Tensor) -> Tensor:
    """Vector play (backlash) operator along the rows (time order) of values (n, ..., k).

    The state starts at the first row and is dragged along when the input moves more than the width away:
    state_t = v_t + (s_{t−1} − v_t)·min(1, w_t/‖s_{t−1} − v_t‖) (k = 1: the scalar play). ``width`` [unit of
    the values]: a constant or per-row widths broadcastable to values.shape[:-1]. (values − state)/width lies in
    the unit disc and encodes the recent direction of motion.
    """
    w = torch.as_tensor(width, dtype=values.dtype, device=values.device)
    rows = tuple(values.shape[:-1])
    try:
        w = w.expand(rows).unsqueeze(-1)
    except RuntimeError:
        raise ValueError(f"width: expected a number or widths broadcastable to {rows}, got shape "
                         f"{tuple(w.shape)}") from None
    if not bool((w >= 0).all()):
        raise ValueError(f"width: expected widths >= 0, got a minimum of {float(w.min())}")
    out = torch.empty_like(values)
    state = values[0].clone()
    for t in range(values.shape[0]):
        state = play_step(state, values[t], w[t])
        out[t] = state
    return out


def play_step(state: Tensor, value: Tensor, width: float | Tensor) -> Tensor:
    """One step of :func:`play_operator`: the new state (..., k) of state (..., k) and input value (..., k),
    width (..., 1) or a number [unit of the values]: value + (state − value)·min(1, width/‖state − value‖)."""
    diff = state - value
    norm = diff.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return value + diff * (width / norm).clamp(max=1.0)


@dataclass
class Split:
    """Inputs and targets of one recording (float64, SI): servo (n, S), x (n, N) displacements,
    features (n, m, 4) from the fitted CC encoder, cc_tip (n, 3), tip (n, 3) and the motion
    memory (n, m, 2) = (ρ − play(ρ))/PLAY_WIDTH (zeros for synthetic data)."""

    servo: Tensor
    x: Tensor
    features: Tensor
    cc_tip: Tensor
    tip: Tensor
    memory: Tensor

    def __len__(self) -> int:
        return self.tip.shape[0]

    def rows(self, index: Tensor) -> Split:
        """The split restricted to rows ``index`` (a boolean mask (n,) or row indices)."""
        return Split(*(getattr(self, f.name)[index] for f in fields(self)))

    @property
    def clarke(self) -> Tensor:
        """(n, 2m) float32 network input: (ρ_re, ρ_im) of every segment."""
        return self.features[..., :2].flatten(-2).float()


def command_split(servo: Tensor, servo_ids: tuple[str, ...], spec: RobotSpec, smap: ServoMap, cc: CalibratedCC,
                  tip: Tensor | None = None) -> Split:
    """The model inputs of servo commands (n, S) [m, ``servo_ids`` column order; time order for the motion
    memory] through the calibration (servo map, fitted CC model); ``tip``: their measured tips (n, 3) [m], or
    None for commands without a measurement (the split's tip is then NaN)."""
    x = smap.command_displacements(spec, servo_ids, servo)
    with torch.no_grad():
        features = cc.encoder(x)
        played = play_operator(features[..., :2], PLAY_WIDTH)
        return encoded_split(servo, x, features, played, cc.tip_from_features(features), tip)


def encoded_split(servo: Tensor, x: Tensor, features: Tensor, played: Tensor, cc_tip: Tensor,
                  tip: Tensor | None = None) -> Split:
    """The Split of n encoded commands: servo (n, S) [m], displacements x (n, N) [m], encoder features
    (n, m, 4), the play state of their ρ (n, m, 2) [m] (:func:`play_operator`; the memory is
    (ρ − played)/PLAY_WIDTH), the CC tips (n, 3) [m] and measured tips (n, 3) [m] or None (NaN)."""
    memory = (features[..., :2] - played) / PLAY_WIDTH
    tip = servo.new_full((servo.shape[0], 3), float("nan")) if tip is None else tip
    return Split(servo, x, features, cc_tip, tip, memory)


def make_split(rec: Recording, spec: RobotSpec, smap: ServoMap, cc: CalibratedCC) -> Split:
    """The model inputs and measured tips of a recording (:func:`command_split`)."""
    return command_split(rec.servo, rec.servo_ids, spec, smap, cc, rec.tip)


def pretrain_and_finetune(params, synthetic_loss, real_loss) -> None:
    """Pre-train ``params`` on a synthetic set (``synthetic_loss()``), then fine-tune them on the recording with the
    synthetic set kept in the loss (rehearsal): ``real_loss() + REHEARSAL·synthetic_loss()``, fewer steps and lr/3."""
    train_full_batch(params, synthetic_loss)
    train_full_batch(params, lambda: real_loss() + REHEARSAL * synthetic_loss(), steps=FINETUNE_STEPS, lr=LR / 3)


def train_full_batch(params, loss_fn, steps: int | None = None, lr: float = LR) -> None:
    """Full-batch Adam on ``loss_fn()`` with a cosine schedule for ``steps`` steps (default :data:`STEPS`, or
    ``$DACR_HARDWARE_STEPS`` where set: read at each call, so it reaches the benchmark's spawned workers too)."""
    if steps is None:
        setting = os.environ.get(STEPS_ENV, "").strip()
        if setting and not (setting.isdigit() and int(setting) > 0):
            raise ValueError(f"{STEPS_ENV}={setting!r}: expected a positive whole number of training steps")
        steps = int(setting) if setting else STEPS
    opt = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for _ in range(steps):
        opt.zero_grad()
        loss_fn().backward()
        opt.step()
        sched.step()


class TipMLP(nn.Module):
    """MLP from raw servo values (``inputs="raw"``, n_inputs = number of servos) or Clarke features
    (``"clarke"``, n_inputs = 2m) to the tip; inputs and outputs standardised with statistics of the
    training split (:meth:`fit_normalization`, part of :meth:`fit`)."""

    def __init__(self, inputs: str, n_inputs: int):
        super().__init__()
        if inputs not in ("raw", "clarke"):
            raise ValueError(f"inputs: expected 'raw' or 'clarke', got {inputs!r}")
        self.inputs = inputs
        self.norm = Standardizer(n_inputs)
        self.net = mlp(n_inputs, 3, HIDDEN, DEPTH, "silu")
        self.register_buffer("tip_mean", torch.zeros(3))
        self.register_buffer("tip_std", torch.ones(3))

    def _input(self, split: Split) -> Tensor:
        return split.servo.float() if self.inputs == "raw" else split.clarke

    def fit_normalization(self, train: Split) -> None:
        self.norm.fit(self._input(train), dtype=NORM_DTYPE)
        self.tip_mean.copy_(train.tip.float().mean(0))
        self.tip_std.copy_(train.tip.float().std(0))

    def from_input(self, inp: Tensor) -> Tensor:
        return self.net(self.norm(inp)) * self.tip_std + self.tip_mean

    def forward(self, split: Split) -> Tensor:
        return self.from_input(self._input(split)).double()

    def fit(self, train: Split) -> None:
        self.fit_normalization(train)
        inp, tip = self._input(train), train.tip.float()
        train_full_batch(self.net.parameters(), lambda: self._loss(self.from_input(inp), tip))

    def _loss(self, pred: Tensor, tip: Tensor) -> Tensor:
        return ((pred - tip) / self.tip_std).pow(2).mean()


class LinearRaw(nn.Module):
    """tip = W·servo + b of the n_servos raw servo values, least squares."""

    def __init__(self, n_servos: int):
        super().__init__()
        self.register_buffer("coef", torch.zeros(n_servos + 1, 3, dtype=torch.float64))

    def fit(self, train: Split) -> None:
        a = torch.cat([train.servo, torch.ones_like(train.servo[:, :1])], 1)
        self.coef = torch.linalg.lstsq(a, train.tip).solution

    def forward(self, split: Split) -> Tensor:
        return torch.cat([split.servo, torch.ones_like(split.servo[:, :1])], 1) @ self.coef


class CCOnly(nn.Module):
    """The calibrated CC model (already fitted); its predictions are precomputed in the split."""

    def fit(self, train: Split) -> None:
        pass

    def forward(self, split: Split) -> Tensor:
        return split.cc_tip


class CCTipResidual(nn.Module):
    """tip = CC(x) + MLP(Clarke features (n_inputs = 2m))·5 mm."""

    def __init__(self, n_inputs: int):
        super().__init__()
        self.norm = Standardizer(n_inputs)
        self.net = mlp(n_inputs, 3, HIDDEN, DEPTH, "silu")

    def forward(self, split: Split) -> Tensor:
        return split.cc_tip + (self.net(self.norm(split.clarke)) * RESIDUAL_TIP_SCALE).double()

    def fit_normalization(self, train: Split) -> None:
        self.norm.fit(train.clarke, dtype=NORM_DTYPE)

    def fit(self, train: Split) -> None:
        self.fit_normalization(train)
        train_full_batch(self.net.parameters(), lambda: (self(train) - train.tip).pow(2).mean() / 1e-6)


class CCClarkeResidual(nn.Module):
    """Per-segment Clarke correction ρ⁽ᵏ⁾ + f([ρ⁽ᵏ⁾/σ, onehot(k)])·0.5 mm, then the CC kinematics of ``cc``
    (σ: the std of the training split's ρ, :meth:`fit_normalization`, part of :meth:`fit`)."""

    history = False

    def __init__(self, cc: CalibratedCC):
        super().__init__()
        self.cc = cc
        m = cc.spec.num_segments
        self.register_buffer("rho_std", torch.tensor(1.0))
        self.register_buffer("onehot", torch.eye(m))
        self.net = mlp(2 + 2 * self.history + m, 2, RESIDUAL_HIDDEN, DEPTH, "silu")

    def fit_normalization(self, train: Split) -> None:
        self.rho_std.copy_(train.features[..., :2].float().std())

    def corrected_features(self, split: Split) -> Tensor:
        rho = split.features[..., :2].float()
        parts = [rho / self.rho_std] + ([split.memory.float()] if self.history else [])
        inp = torch.cat(parts + [self.onehot.expand(*rho.shape[:-1], -1)], -1)
        delta = self.net(inp) * RESIDUAL_RHO_SCALE
        features = split.features.float()
        return torch.cat([features[..., :2] + delta, features[..., 2:]], -1)

    def forward(self, split: Split) -> Tensor:
        """Tip (n, 3) [m], float64; the kinematics run in float32 (3× faster training)."""
        return self.cc.tip_from_features(self.corrected_features(split)).double()

    def objective(self, train: Split) -> Tensor:
        """Mean squared tip error [mm²] on ``train``."""
        return (self(train) - train.tip).pow(2).mean() / 1e-6

    def fit(self, train: Split) -> None:
        self.cc.requires_grad_(False)
        self.fit_normalization(train)
        train_full_batch(self.net.parameters(), lambda: self.objective(train))


class CCClarkeResidualHistory(CCClarkeResidual):
    """:class:`CCClarkeResidual` with the motion memory of each segment as extra input."""

    history = True


def synthetic_split(cc: CalibratedCC, smap: ServoMap, servo_ids: tuple[str, ...], n: int, seed: int,
                    tip_fn=None) -> Split:
    """Synthetic recording of the calibrated CC robot: Clarke features uniform in each segment's bending disc
    (|ρ| ≤ bend·d), x = path length − q (ClarkeDecoder), then the pipeline of real data. ``tip_fn``: displacements
    (n, N) [m] → tips (n, 3) [m] of another model (e.g. the calibrated Cosserat rod) in place of the CC model's."""
    spec = cc.spec
    g = torch.Generator().manual_seed(seed)
    m = spec.num_segments
    reach = torch.tensor([s.bend * s.radius for s in spec.segments], dtype=torch.float64)
    r = reach * torch.rand(n, m, generator=g, dtype=torch.float64).sqrt()
    angle = 2 * math.pi * torch.rand(n, m, generator=g, dtype=torch.float64)
    beta = torch.tensor([s.length for s in spec.segments], dtype=torch.float64).expand(n, m)
    feat = torch.stack([r * angle.cos(), r * angle.sin(), beta, torch.zeros_like(beta)], -1)
    decoder = ClarkeDecoder(spec)
    x = decoder(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - decoder(feat)
    with torch.no_grad():
        features = cc.encoder(x)
        tip = cc.tip_from_features(features) if tip_fn is None else tip_fn(x).to(features.dtype)
    servo = smap.servo_values(spec, servo_ids, x)
    return Split(servo, x, features, tip, tip, torch.zeros_like(features[..., :2]))


class Pretrained(TipMLP):
    """TipMLP pre-trained on a synthetic split of the calibrated CC robot (:func:`synthetic_split` of ``cc``,
    ``smap``, ``servo_ids`` with ``samples`` rows and seed ``synthetic_seed``, drawn in :meth:`fit`), then
    fine-tuned on the recording with the synthetic set kept in the loss (rehearsal)."""

    def __init__(self, inputs: str, n_inputs: int, cc: CalibratedCC, smap: ServoMap, servo_ids: tuple[str, ...],
                 synthetic_seed: int, samples: int = PRETRAIN_SAMPLES):
        super().__init__(inputs, n_inputs)
        self.synthetic_source = (cc, smap, tuple(servo_ids), samples, synthetic_seed)   # not a submodule

    def fit(self, train: Split) -> None:
        self.fit_normalization(train)
        cc, smap, servo_ids, samples, seed = self.synthetic_source
        synthetic = synthetic_split(cc, smap, servo_ids, samples, seed)
        s_inp, s_tip = self._input(synthetic), synthetic.tip.float()
        r_inp, r_tip = self._input(train), train.tip.float()
        pretrain_and_finetune(list(self.net.parameters()), lambda: self._loss(self.from_input(s_inp), s_tip),
                              lambda: self._loss(self.from_input(r_inp), r_tip))


def cc_as_residual(train: Split, cc: CalibratedCC) -> CCClarkeResidual:
    """The calibrated CC model (registry name ``cc``) in the CC Clarke-residual form: a correction network
    whose output layer is zero, so it predicts exactly the CC model's tips — and saves, exports and runs in
    a controller like the learned members (its input scale from ``train``, as a fitted member's)."""
    model = CCClarkeResidual(cc)
    model.fit_normalization(train)
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
    return model.eval()
