"""Uncertainty of hardware tip models (docs/hardware.md, "Uncertainty"): the σ of each prediction (:class:`SigmaModel`
over the terms of :func:`sigma_terms`, fitted to held-out residuals of train-only folds, :mod:`.heldout`; or the
ensemble term alone, :class:`SigmaCalibration`), its scores on offset-removed residuals (:func:`coverage`,
:func:`spearman`) and the out-of-support score of a command (:class:`SupportModel`: the distance of its standardised
Clarke coordinates to the nearest training row over the 99th percentile of the training rows' distances to the
nearest row of another pattern; > 1: the prediction is an extrapolation).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ...checks import check_tensor

SUPPORT_QUANTILE = 0.99
_EXACT = "donot_use_mm_for_euclid_dist"  # no cancellation: a training row is at distance 0 from itself


TERMS = ("ensemble", "disagreement", "support", "bend")


def sigma_terms(preds: Tensor, cc_tip: Tensor, rho: Tensor, support_distance: Tensor) -> dict[str, Tensor]:
    """The inputs of a :class:`SigmaModel` for n commands: preds (K, n, 3) [m] of the K members, cc_tip (n, 3) [m]
    of the calibrated CC model alone, rho (n, m, 2) [m], support_distance (n,) [training std]
    (:meth:`SupportModel.distance`). Returns {"ensemble": members' std (n, 3) [m] (zeros for K = 1),
    "disagreement": |mean − CC| (n, 3) [m], "support": (n, 1), "bend": ‖ρ‖ over all segments (n, 1) [m]}.
    """
    check_tensor(cc_tip, "cc_tip", (3,))
    if preds.dim() != 3 or preds.shape[1:] != cc_tip.shape:
        raise ValueError(f"preds: expected shape (K, {cc_tip.shape[0]}, 3), got {tuple(preds.shape)}")
    check_tensor(rho, "rho", (2,))
    if rho.dim() != 3 or rho.shape[0] != cc_tip.shape[0] or support_distance.shape != (cc_tip.shape[0],):
        raise ValueError(f"rho/support_distance: expected shapes (n, m, 2) and (n,) with n = {cc_tip.shape[0]}, "
                         f"got {tuple(rho.shape)} and {tuple(support_distance.shape)}")
    std = preds.std(0, correction=1) if preds.shape[0] > 1 else torch.zeros_like(preds[0])
    return {"ensemble": std, "disagreement": (preds.mean(0) - cc_tip).abs(),
            "support": support_distance.unsqueeze(-1).to(preds.dtype),
            "bend": rho.flatten(-2).norm(dim=-1, keepdim=True).to(preds.dtype)}


def mean_and_sigma(preds: Tensor, cc_tip: Tensor, rho: Tensor, sigma: SigmaModel,
                   support: SupportModel | None) -> tuple[Tensor, Tensor]:
    """(tip (n, 3) [m] = the mean of the K members' tips preds (K, n, 3) [m], σ (n, 3) [m] of ``sigma``) at
    commands of CC tips cc_tip (n, 3) [m] and Clarke coordinates rho (n, m, 2) [m] (:func:`sigma_terms`;
    the support distance from ``support`` when ``sigma`` has that term, a ValueError when it is None)."""
    if "support" not in sigma.terms:
        dist = rho.new_zeros(rho.shape[0])
    elif support is None:
        raise ValueError("sigma_model: its 'support' term needs the support model, which this model lacks")
    else:
        dist = support.distance(rho)
    return preds.mean(0), sigma(sigma_terms(preds, cc_tip, rho, dist))


class SigmaModel(nn.Module):
    """σ_a² = σ₀² + Σ_t (c_t·f_t,a)² per tip axis a over terms t of :data:`TERMS` (features: :func:`sigma_terms`);
    c_t ≥ 0 and σ₀ [m] fitted by Gaussian maximum likelihood on held-out offset-removed residuals (:meth:`fit`)."""

    def __init__(self, terms: Sequence[str], coefficients: Sequence[float], floor: float):
        super().__init__()
        unknown = [t for t in terms if t not in TERMS]
        if unknown or not terms or len(coefficients) != len(terms) or len(set(terms)) != len(terms):
            raise ValueError(f"terms/coefficients: expected distinct terms of {TERMS} and one coefficient each, "
                             f"got {list(terms)} and {list(coefficients)}")
        self.terms = tuple(terms)
        self.register_buffer("coefficients", torch.tensor([float(c) for c in coefficients], dtype=torch.float64))
        self.register_buffer("floor", torch.tensor(float(floor), dtype=torch.float64))

    def variance(self, features: dict[str, Tensor]) -> Tensor:
        """σ² (n, 3) [m²] from the features of :func:`sigma_terms` (only this model's terms are read)."""
        missing = [t for t in self.terms if t not in features]
        if missing:
            raise ValueError(f"features: expected the terms {list(self.terms)}, missing {missing}")
        ref = features[self.terms[0]]
        var = (self.floor.to(ref.dtype) ** 2).expand(*ref.shape[:-1], 3)
        for c, t in zip(self.coefficients.to(ref.dtype), self.terms, strict=True):
            var = var + (c * features[t]) ** 2
        return var

    def forward(self, features: dict[str, Tensor]) -> Tensor:
        """σ (n, 3) [m]."""
        return self.variance(features).sqrt()

    def to_dict(self) -> dict:
        """Plain {"terms", "coefficients", "floor" [m]} (weights-only checkpoints)."""
        return {"terms": list(self.terms), "coefficients": self.coefficients.tolist(), "floor": float(self.floor)}

    @classmethod
    def from_dict(cls, d: dict) -> SigmaModel:
        return cls(d["terms"], d["coefficients"], d["floor"])

    def describe(self) -> str:
        units = {"ensemble": "", "disagreement": "", "support": " mm", "bend": ""}
        parts = [f"{t} {c * (1e3 if t == 'support' else 1):.3g}{units[t]}" for t, c in
                 zip(self.terms, self.coefficients.tolist(), strict=True)]
        return ", ".join(parts) + f", floor {float(self.floor) * 1e3:.2f} mm"

    @classmethod
    def fit(cls, terms: Sequence[str], features: dict[str, Tensor], residual: Tensor, iters: int = 200) -> SigmaModel:
        """Maximise Σ log N(residual; 0, σ²) over the coefficients and σ₀ (all ≥ 0); residual (n, 3) [m],
        held out and offset-removed (the lab's metric forgives a constant offset)."""
        check_tensor(residual, "residual", (3,))
        if residual.dim() != 2 or residual.shape[0] < 2:
            raise ValueError(f"residual: expected shape (n, 3) with n >= 2, got {tuple(residual.shape)}")
        cls(terms, [1.0] * len(terms), 0.0).variance(features)          # validates terms and features
        r2 = residual.double().pow(2)
        unit = float(r2.mean().sqrt())                                     # optimise in units of the rms residual
        feats = [features[t].double() for t in terms]
        scales = [float(f.pow(2).mean().sqrt()) or 1.0 for f in feats]     # and each feature in its rms
        for f in feats:
            if f.shape[0] != residual.shape[0]:
                raise ValueError(f"features: expected {residual.shape[0]} rows like residual, got {f.shape[0]}")
        z = [f / s for f, s in zip(feats, scales, strict=True)]
        log_p = torch.full((len(terms) + 1,), -1.0, dtype=torch.float64, requires_grad=True)
        opt = torch.optim.LBFGS([log_p], max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            var = log_p[-1].exp() ** 2 + sum((log_p[i].exp() * zi) ** 2 for i, zi in enumerate(z))
            loss = (torch.log(var) + r2 / unit**2 / var).mean()
            loss.backward()
            return loss

        opt.step(closure)
        p = log_p.detach().exp().tolist()
        return cls(terms, [p[i] * unit / scales[i] for i in range(len(terms))], p[-1] * unit)


class SigmaCalibration(nn.Module):
    """σ_cal = sqrt((s·σ)² + σ₀²) per axis from the ensemble std alone (the ``ensemble`` term of
    :class:`SigmaModel`); s and σ₀ fitted on held-out residuals (see the module doc)."""

    def __init__(self, scale: float = 1.0, floor: float = 0.0):
        super().__init__()
        self.register_buffer("scale", torch.tensor(float(scale), dtype=torch.float64))
        self.register_buffer("floor", torch.tensor(float(floor), dtype=torch.float64))

    def forward(self, std: Tensor) -> Tensor:
        """Ensemble std (..., 3) [m] → calibrated std (..., 3) [m]."""
        return ((self.scale.to(std.dtype) * std) ** 2 + self.floor.to(std.dtype) ** 2).sqrt()

    def as_model(self) -> SigmaModel:
        """The same σ as a :class:`SigmaModel` of the ``ensemble`` term (coefficient s, floor σ₀)."""
        return SigmaModel(("ensemble",), [float(self.scale)], float(self.floor))

    @classmethod
    def fit(cls, residual: Tensor, std: Tensor, iters: int = 200) -> SigmaCalibration:
        """Maximise Σ log N(r; 0, σ_cal²) over (s, σ₀) ≥ 0: residual r (offset-removed, held out), std (n, 3) [m]."""
        check_tensor(residual, "residual", (3,))
        check_tensor(std, "std", (3,))
        if residual.shape != std.shape or residual.shape[0] < 2:
            raise ValueError(f"residual/std: expected equal shapes (n, 3) with n >= 2, got "
                             f"{tuple(residual.shape)} and {tuple(std.shape)}")
        model = SigmaModel.fit(("ensemble",), {"ensemble": std}, residual, iters)
        return cls(float(model.coefficients[0]), float(model.floor))


def coverage(residual: Tensor, sigma: Tensor, k: float = 2.0) -> float:
    """Fraction of the entries of residual (n, 3) with |r| ≤ k·σ (per axis, σ (n, 3) in the same unit)."""
    if residual.shape != sigma.shape:
        raise ValueError(f"residual/sigma: expected equal shapes, got {tuple(residual.shape)} and {tuple(sigma.shape)}")
    return float((residual.abs() <= k * sigma).double().mean())


def spearman(a: Tensor, b: Tensor) -> float:
    """Spearman rank correlation of two (n,) tensors (ties broken by order; nan if one is constant)."""
    if a.shape != b.shape or a.dim() != 1 or a.shape[0] < 2:
        raise ValueError(f"a/b: expected equal shapes (n,) with n >= 2, got {tuple(a.shape)} and {tuple(b.shape)}")
    ranks = [x.argsort().argsort().double() for x in (a, b)]
    if any(bool((x == x[0]).all()) for x in (a, b)):
        return float("nan")
    return float(torch.corrcoef(torch.stack(ranks))[0, 1])


class SupportModel(nn.Module):
    """Out-of-support score of commands from their Clarke coordinates ρ (..., m, 2) [m], m = ``num_segments`` (module
    docstring); the threshold is the ``quantile`` of the training rows' cross-pattern distances (:meth:`fit`)."""

    def __init__(self, num_segments: int, quantile: float = SUPPORT_QUANTILE):
        super().__init__()
        self.num_segments, self.quantile = int(num_segments), float(quantile)
        dim = 2 * self.num_segments
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("std", torch.ones(dim, dtype=torch.float64))
        self.register_buffer("points", torch.zeros(0, dim, dtype=torch.float64))   # standardised training rows
        self.register_buffer("threshold", torch.tensor(1.0, dtype=torch.float64))

    def fit(self, train_rho: Tensor, labels: Sequence[str] | None = None) -> SupportModel:
        """Fit on the Clarke coordinates (n, m, 2) [m] of the training commands and their n pattern labels
        (a row's own pattern is excluded when the threshold is set; None: every row is its own pattern,
        plain leave-one-out); returns the model."""
        check_tensor(train_rho, "train_rho", (self.num_segments, 2))
        if train_rho.dim() != 3 or train_rho.shape[0] < 2:
            raise ValueError(f"train_rho: expected shape (n, {self.num_segments}, 2) with n >= 2, got "
                             f"{tuple(train_rho.shape)}")
        points = train_rho.flatten(1).double()
        if labels is not None and len(labels) != points.shape[0]:
            raise ValueError(f"labels: expected {points.shape[0]} labels (one per row), got {len(labels)}")
        self.mean.copy_(points.mean(0))
        self.std.copy_(points.std(0).clamp_min(1e-12))
        self.points = (points - self.mean) / self.std
        groups = torch.arange(points.shape[0])        # no labels, or one pattern only: leave-one-out
        if labels is not None and len(set(labels)) > 1:
            groups = torch.from_numpy(np.unique(labels, return_inverse=True)[1])
        dist = torch.cdist(self.points, self.points, compute_mode=_EXACT)
        dist[groups[:, None] == groups[None, :]] = float("inf")
        self.threshold.copy_(torch.quantile(dist.min(1).values, self.quantile))
        return self

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        points = state_dict.get(prefix + "points")
        if isinstance(points, Tensor):                # the number of training rows is the stored one
            self.points = torch.empty_like(points, dtype=self.points.dtype)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _standardised(self, rho: Tensor) -> Tensor:
        check_tensor(rho, "rho", (self.num_segments, 2))
        return (rho.flatten(-2).double() - self.mean) / self.std

    def distance(self, rho: Tensor) -> Tensor:
        """Standardised distance of each command's ρ (..., m, 2) [m] to the nearest training row (...)."""
        z = self._standardised(rho)
        dist = torch.cdist(z.reshape(-1, z.shape[-1]), self.points, compute_mode=_EXACT)
        return dist.min(1).values.reshape(z.shape[:-1])

    def forward(self, rho: Tensor) -> Tensor:
        """Out-of-support score (...,): > 1 means outside the training support."""
        return self.distance(rho) / self.threshold
