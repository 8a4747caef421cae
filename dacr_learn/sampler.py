"""A learned multi-solution IK sampler: a conditional normalizing flow of the joints given the target (docs/ik.md).

:class:`ClarkeSampler` models p(x | target), the distribution of the joint configurations that reach a tip pose
(or position), so that its samples seed the IK solver's refinement (:func:`dacr_learn.ik.solve_ik`, ``seeds``).
The flow is ``zuko.flows.NSF`` (coupling, ``passes=2``) on standardised variables y:

- ``features="clarke"``: y = standardise(squash⁻¹(x)), x the actuated Clarke features (``models.actuated_columns``
  order). The squash maps ℝᴰ onto the robot's limits: a box coordinate (β, α) by mid + half·tanh(v), a bending
  pair v ∈ ℝ² into its disk ‖ρ‖ ≤ d·bend by ρ = d·bend·tanh(‖v‖)·v/‖v‖, so every sample lies inside the limits.
- ``features="raw"``: y = standardise(q); a sample is encoded to features and projected onto the limits
  (:meth:`~dacr_learn.limits.Limits.project`); the training noise (``SamplerModule.noise``) keeps the density finite.

Conditioning c (10,): the standardised :func:`~dacr_learn.models.pose_to_vector` of the target and a flag, 1 when
the rotation is given (else its entries are 0). No Lightning; trained by :class:`~.training_sampler.SamplerModule`.
"""
from __future__ import annotations

import math

import torch
import zuko
from torch import Tensor, nn

from .checks import F64, as_floating, check_choice
from .clarke_space import ClarkeSpace
from .layers import ClarkeEncoder
from .models import ACTIVATIONS, FEATURE_MODES, Standardizer, actuated_selection, pose_to_vector
from .robot import RobotSpec

__all__ = ["ClarkeSampler", "LimitSquash"]

EDGE = 1e-6          # a training sample on a limit is moved this far inside (in units of the half-range) before atanh


def _tanh_ratio(s: Tensor) -> Tensor:
    """tanh(s)/s, 1 at s = 0 (s ≥ 0)."""
    small = s < 1e-4
    return torch.where(small, 1 - s * s / 3, torch.tanh(s) / torch.where(small, torch.ones_like(s), s))


def _atanh_ratio(r: Tensor) -> Tensor:
    """atanh(r)/r, 1 at r = 0 (0 ≤ r < 1)."""
    small = r < 1e-4
    return torch.where(small, 1 + r * r / 3, torch.atanh(r) / torch.where(small, torch.ones_like(r), r))


class LimitSquash:
    """The bijection between ℝᴰ and the (open) admissible set of a robot's actuated features (module docstring).

    :meth:`forward`: v (..., D) → features x (..., D) inside the limits; :meth:`inverse`: x → v (a feature on a
    limit is first moved :data:`EDGE` of its half-range inside). The limits (float64,
    :class:`~dacr_learn.clarke_space.ClarkeSpace`) are cast to the input's dtype: a float64 sample is inside them.
    """

    def __init__(self, space: ClarkeSpace):
        limits = space.limits
        self.rho_cols, self.rho_max = limits.disks, limits.radius
        self.box_cols = torch.isfinite(limits.lower).nonzero().squeeze(-1)
        lower, upper = limits.lower[self.box_cols], limits.upper[self.box_cols]
        self.box_mid, self.box_half = (lower + upper) / 2, (upper - lower) / 2

    def forward(self, v: Tensor) -> Tensor:
        x = v.clone()
        if self.box_cols.numel():
            mid, half = self.box_mid.to(v.dtype), self.box_half.to(v.dtype)
            x[..., self.box_cols] = mid + half * torch.tanh(v[..., self.box_cols])
        pair = v[..., self.rho_cols]                                                  # (..., m, 2)
        norm = torch.linalg.vector_norm(pair, dim=-1, keepdim=True)
        x[..., self.rho_cols] = self.rho_max.to(v.dtype).unsqueeze(-1) * pair * _tanh_ratio(norm)
        return x

    __call__ = forward

    def inverse(self, x: Tensor) -> Tensor:
        v = x.clone()
        if self.box_cols.numel():
            mid, half = self.box_mid.to(x.dtype), self.box_half.to(x.dtype)
            v[..., self.box_cols] = torch.atanh(((x[..., self.box_cols] - mid) / half).clamp(-1 + EDGE, 1 - EDGE))
        pair = x[..., self.rho_cols] / self.rho_max.to(x.dtype).unsqueeze(-1)
        norm = torch.linalg.vector_norm(pair, dim=-1, keepdim=True)
        inside = norm.clamp(max=1 - EDGE)
        shrink = torch.where(norm > inside, inside / norm.clamp_min(1e-30), torch.ones_like(norm))
        v[..., self.rho_cols] = pair * shrink * _atanh_ratio(inside)
        return v


class ClarkeSampler(nn.Module):
    """Conditional normalizing flow of a robot's joint configurations given a tip pose or position.

    features: "clarke" | "raw" (module docstring); transforms: coupling transforms; width, depth, activation
    (``models.ACTIVATIONS``): each transform's network; bins: spline bins. Built from a ``train.py`` checkpoint's
    hyper-parameters by :func:`~dacr_learn.compositional.model_from_hparams` (task "sampler").
    ``position_trained`` (a buffer): whether training hid some targets' rotations (position-only targets allowed).
    """

    def __init__(self, spec: RobotSpec, features: str = "clarke", transforms: int = 4, width: int = 128,
                 depth: int = 2, activation: str = "relu", bins: int = 8):
        super().__init__()
        check_choice("features", features, FEATURE_MODES)
        check_choice("activation", activation, ACTIVATIONS)
        for name, value, least in (("transforms", transforms, 1), ("width", width, 1), ("depth", depth, 1),
                                   ("bins", bins, 2)):
            if not (isinstance(value, int) and value >= least):
                raise ValueError(f"{name}: expected an integer >= {least}, got {value!r}")
        self.spec, self.features, self.length = spec, features, spec.total_length
        self.space = ClarkeSpace(spec)                                  # float64 maps f ↔ q and the limits
        self.num_features = spec.num_actuated_features
        self.dim = self.num_features if features == "clarke" else spec.num_joints
        self.encoder = ClarkeEncoder(spec)
        self.register_buffer("selection", actuated_selection(spec))
        self.squash = LimitSquash(self.space)
        self.target_norm = Standardizer(9)
        self.out_norm = Standardizer(self.dim)
        self.register_buffer("position_trained", torch.zeros((), dtype=torch.bool))
        self.flow = zuko.flows.NSF(features=self.dim, context=10, transforms=transforms, bins=bins, passes=2,
                                   randperm=True, hidden_features=(width,) * depth, activation=ACTIVATIONS[activation])

    # ---- the variables and the condition
    def variables(self, q: Tensor) -> Tensor:
        """Joint vectors (..., N) → the flow's unstandardised variables (..., dim): squash⁻¹ of the actuated
        features ("clarke") or q itself ("raw")."""
        if self.features == "raw":
            return q
        return self.squash.inverse(self.encoder(q).flatten(-2) @ self.selection.to(q.dtype).mT)

    def fit_normalization(self, q: Tensor, pose: Tensor) -> None:
        """Standardisations from training joint vectors (n, N) and poses (n, 4, 4)."""
        self.target_norm.fit(pose_to_vector(pose, self.length))
        self.out_norm.fit(self.variables(q))

    def condition(self, target: Tensor, hide_rotation: Tensor | None = None) -> Tensor:
        """Targets (B, 4, 4) poses or (B, 3) positions [m] → contexts (B, 10). ``hide_rotation`` (B,) bool hides
        the rotation of those poses (training)."""
        dtype = self.target_norm.mean.dtype
        if target.shape[-1] == 3 and target.dim() == 2:
            vec = torch.cat([target.to(dtype) / self.length, torch.zeros(target.shape[0], 6, dtype=dtype,
                                                                         device=target.device)], -1)
            c = self.target_norm(vec)
            shown = torch.zeros(target.shape[0], 1, dtype=dtype, device=target.device)
        else:
            c = self.target_norm(pose_to_vector(target.to(dtype), self.length))
            shown = torch.ones(target.shape[0], 1, dtype=dtype, device=target.device)
            if hide_rotation is not None:
                shown = shown * (~hide_rotation).to(dtype).unsqueeze(-1)
        return torch.cat([c[:, :3], c[:, 3:] * shown, shown], -1)

    def log_prob(self, q: Tensor, target: Tensor, hide_rotation: Tensor | None = None,
                 noise: float = 0.0) -> Tensor:
        """(B,) log-density of the standardised variables of joint vectors q (B, N) given the targets (B, 4, 4) or
        (B, 3) (natural log, flow units: standardised variables), with Gaussian ``noise`` of that std added to the
        standardised variables first (training)."""
        y = self.out_norm(self.variables(q))
        if noise:
            y = y + noise * torch.randn_like(y)
        return self.flow(self.condition(target, hide_rotation)).log_prob(y)

    # ---- sampling
    def check_target(self, target) -> Tensor:
        """Validated targets: (B, 4, 4) poses or (B, 3) positions, finite, B ≥ 1 (ValueError naming the problem)."""
        target = as_floating(target, "target")
        is_pose = target.dim() == 3 and target.shape[-2:] == (4, 4)
        is_position = target.dim() == 2 and target.shape[-1] == 3
        if not (is_pose or is_position) or target.shape[0] == 0:
            raise ValueError(f"target: expected (B, 4, 4) tip poses or (B, 3) tip positions [m], B >= 1, "
                             f"got shape {tuple(target.shape)}")
        if not torch.isfinite(target).all():
            raise ValueError("target: expected finite values, got NaN/inf entries")
        if is_position and not bool(self.position_trained):
            raise ValueError("target: this sampler was trained on whole poses only (position_fraction 0); "
                             "give (B, 4, 4) poses, or train with position_fraction > 0 for (B, 3) positions")
        return target

    @torch.no_grad()
    def sample_variables(self, target: Tensor, count: int, temperature: float = 1.0) -> Tensor:
        """(B, count, dim) unstandardised variables drawn for each target (base samples scaled by ``temperature``)."""
        target = self.check_target(target)
        if not (isinstance(count, int) and count >= 1):
            raise ValueError(f"count: expected an integer >= 1 samples per target, got {count!r}")
        if not (isinstance(temperature, (int, float)) and 0 < temperature and math.isfinite(temperature)):
            raise ValueError(f"temperature: expected a finite number > 0, got {temperature!r}")
        b = target.shape[0]
        context = self.condition(target).repeat_interleave(count, 0)                      # (B·count, 10)
        dist = self.flow(context)
        z = dist.base.sample() * temperature
        y = dist.transform.inv(z)
        return self.out_norm.inverse(y).view(b, count, self.dim)

    @torch.no_grad()
    def sample_features(self, target, count: int, temperature: float = 1.0) -> Tensor:
        """``count`` actuated-feature samples per target (B, count, D) float64 [m, rad], inside the limits: the
        ``seeds`` of :func:`dacr_learn.ik.solve_ik`. target: (B, 4, 4) tip poses or (B, 3) tip positions [m]
        (positions need a model trained with ``position_fraction`` > 0). "raw" samples are encoded, then projected.
        """
        v = self.sample_variables(target, count, temperature)
        if self.features == "clarke":
            return self.squash(v.to(F64))
        return self.space.limits.project(self.space.features(v.to(F64)))

    @torch.no_grad()
    def sample(self, target, count: int, temperature: float = 1.0) -> Tensor:
        """``count`` joint vectors per target (B, count, N) float64, on the displacement constraint, inside the
        limits."""
        return self.space.joints(self.sample_features(target, count, temperature))
