"""Held-out predictions of a hardware model on the train-only selection folds, and the σ model fitted to them.

A σ model (:class:`~.uncertainty.SigmaModel`) needs residuals the model did not train on, without the
validation recording: per fold of :func:`~.selection.proxy_masks` the CC model is refitted on the training
rows (:func:`~.selection.make_folds`), the model is trained there once per seed, and on the held-out rows the
σ features (:func:`~.uncertainty.sigma_terms`) and the offset-removed residual of the ensemble mean are kept.
"""
from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass

import torch
from torch import Tensor

from ..deploy.uncertainty import SigmaCalibration, SigmaModel, SupportModel, sigma_terms
from .pool import TaskPool
from .selection import PROXIES, Fold, fold_predictions, make_folds, model_seeds, proxy_masks

# The σ model saved with a hardware model: σ² = σ₀² + (c·‖ρ‖)² (chosen on train only: docs/hardware.md,
# "Uncertainty"), fitted on the singles → pairs fold (the cheapest: one fold, trained on the single-segment rows).
SIGMA_TERMS = ("bend",)
SIGMA_PROXIES = ("extrap",)


@dataclass
class HeldOut:
    """One fold's held-out rows: member tips (K, n, 3), CC tips, measured tips (n, 3) [m], ρ (n, m, 2) [m]
    and the support distance (n,) to the fold's training rows."""

    fold: str
    preds: Tensor
    cc_tip: Tensor
    tip: Tensor
    rho: Tensor
    support: Tensor

    def features(self) -> dict[str, Tensor]:
        return sigma_terms(self.preds, self.cc_tip, self.rho, self.support)

    def residual(self) -> Tensor:
        """Offset-removed residual (n, 3) [m] of the ensemble mean (ē: the mean over this fold's rows)."""
        e = self.preds.mean(0) - self.tip
        return e - e.mean(0)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def held_out(name: str, ctx, test, train_labels: Sequence[str], seeds: Sequence[int], fold: str = "") -> HeldOut:
    """Train model ``name`` once per seed on ``ctx.train`` (a :class:`~.registry.FitContext`) and predict ``test``
    (:func:`~.selection.fold_predictions`)."""
    block = Fold(fold, ctx, test, train_labels=tuple(train_labels))
    return _block(block, torch.stack([fold_predictions(name, block, seed) for seed in model_seeds(name, seeds)]))


def _block(fold: Fold, preds: Tensor, tag: str | None = None) -> HeldOut:
    """:class:`HeldOut` of the members' predictions preds (K, n, 3) [m] on ``fold.test``, the support distance to
    the fold's training rows (their pattern labels ``fold.train_labels``)."""
    support = SupportModel(fold.ctx.cc.spec.num_segments).fit(fold.ctx.train.features[..., :2],
                                                              list(fold.train_labels))
    rho = fold.test.features[..., :2]
    return HeldOut(fold.name if tag is None else tag, preds, fold.test.cc_tip, fold.test.tip, rho,
                   support.distance(rho))


def held_out_folds(setup, name: str, seeds: Sequence[int], proxies: Sequence[str] = PROXIES,
                   log=None, pool: TaskPool | None = None) -> list[HeldOut]:
    """:class:`HeldOut` of every fold of the given proxies on the training recording of a
    :class:`~.benchmark.Setup` (``log``: optional callable reporting each fold; ``pool``: where the fits
    run, default in this process)."""
    return collect_held_out(submit_held_out(pool or TaskPool(), setup, name, seeds, proxies), log)


def submit_held_out(pool: TaskPool, setup, name: str, seeds: Sequence[int],
                    proxies: Sequence[str] = PROXIES) -> list[tuple[str, list[Future]]]:
    """The fits of :func:`held_out_folds` handed to ``pool`` (one task per fold and seed; the folds' CC
    refits run here): [(fold, [future of timed(held_out) per seed])], for :func:`collect_held_out`."""
    labels = setup.train_rec.labels
    out = []
    for proxy, masks in proxy_masks(labels, proxies).items():
        for fold, (fold_name, train_rows, _) in zip(make_folds(setup.train_rec, setup.spec, setup.smap, masks,
                                                               setup.cc_options),
                                                    masks, strict=True):
            train_labels = [lb for lb, t in zip(labels, train_rows, strict=True) if t]
            tag = f"{proxy}:{fold_name}"
            out.append((tag, [pool.submit(held_out, name, fold.ctx, fold.test, train_labels, [seed], tag)
                              for seed in model_seeds(name, seeds)]))
    return out


def collect_held_out(pending: list[tuple[str, list[Future]]], log=None) -> list[HeldOut]:
    """:class:`HeldOut` per fold of :func:`submit_held_out`'s fits, the seeds' predictions stacked in order."""
    out = []
    for tag, futures in pending:
        parts = [f.result()[0] for f in futures]
        out.append(HeldOut(**{**parts[0].to_dict(), "preds": torch.cat([p.preds for p in parts])}))
        if log is not None:
            log(f"held-out σ features: fold {tag} done")
    return out


def held_out_from_selection(selection, name: str, seeds: Sequence[int],
                            proxies: Sequence[str] = SIGMA_PROXIES) -> list[HeldOut] | None:
    """:class:`HeldOut` of the ``proxies`` folds built from the selection proxies' own fits of model ``name``
    (a :class:`~.benchmark.SelectionResult`: the same fold, model and seeds as :func:`held_out` would fit
    again), or None when the selection did not fit ``name`` on those folds with exactly ``seeds``."""
    want = model_seeds(name, seeds)
    if name not in selection.predictions or selection.seeds.get(name) != want:
        return None
    if any(proxy not in selection.folds or proxy not in selection.predictions[name] for proxy in proxies):
        return None
    return [_block(fold, torch.stack(selection.predictions[name][proxy][fold.name]), f"{proxy}:{fold.name}")
            for proxy in proxies for fold in selection.folds[proxy]]


def fit_sigma_model(blocks: Sequence[HeldOut], terms: Sequence[str]) -> SigmaModel:
    """:meth:`SigmaModel.fit` on the held-out rows of all blocks (residuals offset-removed per block)."""
    if not blocks:
        raise ValueError("blocks: expected at least one held-out fold, got none")
    feats = [b.features() for b in blocks]
    return SigmaModel.fit(terms, {t: torch.cat([f[t] for f in feats]) for t in feats[0]},
                          torch.cat([b.residual() for b in blocks]))


def sigma_models_of(blocks: Sequence[HeldOut],
                    terms: Sequence[str] = SIGMA_TERMS) -> tuple[SigmaCalibration, SigmaModel]:
    """(ensemble-only σ calibration — the σ of a model saved without a σ model —, σ model with ``terms``), both fitted
    on the held-out rows of ``blocks`` (:func:`held_out_folds`, or :func:`submit_held_out` in a pool)."""
    residual = torch.cat([b.residual() for b in blocks])
    std = torch.cat([b.features()["ensemble"] for b in blocks])
    return SigmaCalibration.fit(residual, std), fit_sigma_model(blocks, terms)
