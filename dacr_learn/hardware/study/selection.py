"""Choosing a model on the training recording alone: two selection proxies and the default model.

Both proxies are the offset-removed tip RMSE [mm] on held-out rows of the training recording, the CC model refitted
in every fold (docs/hardware.md, "Choosing the default model on training data alone"): ``cv``, leave-one-pattern-
family-out cross-validation over the families of :func:`pattern_family`; ``extrap``, singles → pairs. Labels
without a family raise. :data:`DEFAULT_PROXIES` is ``extrap`` only (the family CV costs ~4× more).
:func:`choose_cc_variant` picks the CC variant (:data:`CC_VARIANTS`) by the CC model's own ``extrap``;
:func:`default_choice` picks the default model (the one-standard-error rule).
"""
from __future__ import annotations

import re
import time
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ...robot import RobotSpec
from ..ccmodel import CalibratedCC, fit_cc
from ..learned import Split, make_split
from ..metrics import offset_removed_rmse
from ..recording import Recording
from ..servo_map import ServoMap
from .registry import FitContext, build_model, complexity, model_info

CC_VARIANTS: dict[str, dict] = {"base": {}, "strain": {"pretension_strain": True}}   # name → CalibratedCC options
PROXIES = ("cv", "extrap")
SELECTION_PROXY = "extrap"
DEFAULT_PROXIES = (SELECTION_PROXY,)
# The noise of a proxy: a bootstrap over the held-out pattern groups (and over the proxy seeds), the groups drawn
# alike for every model so that differences between models are paired (:func:`bootstrap_replicates`).
BOOTSTRAP_REPLICATES = 2000
BOOTSTRAP_SEED = 0
# The one-standard-error rule (:func:`default_choice`): a candidate is tied with the best when its proxy is worse
# by at most TIE_SIGMAS standard deviations of the bootstrapped difference between the two.
TIE_SIGMAS = 1.0
_PAIR = re.compile(r"pair(\d\d)")
_SINGLE = re.compile(r"(^|_)(seg\d+|tendon\d+)")


def pattern_family(label: str) -> str:
    """``single`` or ``pair<jk>`` from a pattern label (``rep1_seg2_dir90``, ``rep1_pair13_opp_dir0``…)."""
    pair = _PAIR.search(label)
    if pair:
        return "pair" + pair.group(1)
    if _SINGLE.search(label):
        return "single"
    raise ValueError(f"pattern label {label!r}: expected one naming a single segment or tendon "
                     f"('seg<k>', 'tendon<k>') or a pair of segments ('pair<jk>')")


def pattern_group(label: str) -> str:
    """The pattern a row belongs to, for the bootstrap: its label without the repetition prefix and the hold
    suffix (``rep1_pair13_same_dir60_hold`` → ``pair13_same_dir60``): the rows of one pattern move together, so
    they are drawn together."""
    return re.sub(r"_hold$", "", re.sub(r"^rep\d+_", "", label))


def proxy_masks(labels: Sequence[str], proxies: Sequence[str] = PROXIES
                ) -> dict[str, list[tuple[str, np.ndarray, np.ndarray]]]:
    """{proxy: [(fold name, train rows (n,) bool, test rows (n,) bool), …]} from pattern labels,
    for each of ``proxies`` (in the order given)."""
    unknown = [p for p in proxies if p not in PROXIES]
    if unknown or not proxies:
        raise ValueError(f"proxies: expected one or more of {PROXIES}, got {list(proxies)}")
    fam = np.array([pattern_family(label) for label in labels])
    names = sorted(set(fam), key=lambda f: (f != "single", f))
    if "single" not in names or len(names) < 2:
        raise ValueError(f"pattern families: expected 'single' and at least one pair family, got {names}")
    pairs = fam != "single"
    masks = {"cv": [(str(f), fam != f, fam == f) for f in names],
             "extrap": [("singles_to_pairs", ~pairs, pairs)]}
    return {p: masks[p] for p in proxies}


@dataclass
class Fold:
    """One proxy fold: the context (CC refitted on the training rows) and the held-out test rows."""

    name: str
    ctx: FitContext
    test: Split
    groups: tuple[str, ...] = ()      # the pattern group of each test row (:func:`pattern_group`), for the bootstrap
    train_labels: tuple[str, ...] = ()   # the pattern labels of the training rows (e.g. for a support model)


def make_folds(rec: Recording, spec: RobotSpec, smap: ServoMap,
               masks: list[tuple[str, np.ndarray, np.ndarray]], cc_options: dict | None = None,
               cache_dir=None) -> list[Fold]:
    """Refit the calibrated CC model (``CalibratedCC(spec, **cc_options)``) on each fold's training rows
    and split the recording (``cache_dir``: the folds' :attr:`~.registry.FitContext.cache_dir`)."""
    x = smap.displacements(spec, rec)
    folds = []
    for name, tr, te in masks:
        tr, te = torch.from_numpy(tr), torch.from_numpy(te)
        cc = CalibratedCC(spec, **(cc_options or {}))
        fit_cc(cc, x[tr], rec.tip[tr])
        cc.requires_grad_(False)
        split = make_split(rec, spec, smap, cc)
        labels = list(rec.labels)
        folds.append(Fold(name, FitContext(cc, smap, rec.servo_ids, split.rows(tr), cache_dir), split.rows(te),
                          tuple(pattern_group(lb) for lb, t in zip(labels, te.tolist(), strict=True) if t),
                          tuple(lb for lb, t in zip(labels, tr.tolist(), strict=True) if t)))
    return folds


def fold_predictions(model_name: str, fold: Fold, seed: int) -> Tensor:
    """Tips (n_test, 3) [m] that a model trained on the fold's rows (seed ``seed``) predicts on its test rows."""
    model = build_model(model_name, fold.ctx, seed)
    model.fit(fold.ctx.train)
    with torch.no_grad():
        return model.eval()(fold.test).detach().to(torch.float64)


def fold_rmse(model_name: str, fold: Fold, seed: int) -> float:
    """Offset-removed RMSE [mm] of a model trained on the fold's rows, on its test rows."""
    return float(offset_removed_rmse(fold_predictions(model_name, fold, seed), fold.test.tip)) * 1e3


def model_seeds(name: str, seeds: Sequence[int]) -> list[int]:
    """The seeds a model is fitted with: the first only for a deterministic model (the same for every seed)."""
    return list(seeds)[:1] if model_info(name).deterministic else list(seeds)


def summarize_scores(rmse: dict[str, dict[str, list[float]]], seeds: list[int], seconds: float,
                     replicates: Mapping[str, Tensor] | None = None) -> dict:
    """{proxy: mean over folds [mm], proxy + "_folds": {fold: mean over seeds}, proxy + "_per_seed", "seeds",
    "seconds"} from {proxy: {fold: [RMSE [mm] per seed]}}; with ``replicates`` ({proxy: (B,) [mm]},
    :func:`bootstrap_replicates`) also proxy + "_std", the proxy's uncertainty."""
    out: dict = {}
    for proxy, folds in rmse.items():
        per = {fold: float(np.mean(values)) for fold, values in folds.items()}
        out[proxy] = round(float(np.mean(list(per.values()))), 4)
        if replicates is not None and proxy in replicates:
            out[proxy + "_std"] = round(float(replicates[proxy].std()), 4)
        out[proxy + "_folds"] = {k: round(v, 4) for k, v in per.items()}
        out[proxy + "_per_seed"] = [round(float(v), 4) for v in np.mean(list(folds.values()), axis=0)]
    out["seeds"] = seeds
    out["seconds"] = round(seconds, 2)
    return out


def group_weights(groups: Sequence[str], replicates: int = BOOTSTRAP_REPLICATES,
                  generator: torch.Generator | None = None) -> Tensor:
    """Bootstrap weights (B, n) of n rows in pattern groups ``groups`` (n,): each replicate draws as many groups
    as there are, with replacement, and a row's weight is the number of times its group was drawn."""
    names = sorted(set(groups))
    if not names:
        raise ValueError("groups: expected the pattern group of at least one row, got none")
    index = torch.tensor([names.index(g) for g in groups])
    draw = torch.randint(len(names), (replicates, len(names)), generator=generator)
    counts = torch.nn.functional.one_hot(draw, len(names)).sum(1).to(torch.float64)     # (B, groups): times drawn
    return counts[:, index]


def weighted_rmse(error: Tensor, weights: Tensor) -> Tensor:
    """Offset-removed RMSE (B,) of errors (n, 3) under row weights (B, n) (the weighted mean error removed;
    unit of ``error``): sqrt(Σ w‖e − ē_w‖² / Σ w)."""
    total = weights.sum(-1)
    mean = weights @ error / total[:, None]
    square = weights @ error.pow(2).sum(-1) / total - mean.pow(2).sum(-1)
    return square.clamp(min=0).sqrt()


def fold_weights(groups: Mapping[str, Sequence[str]], replicates: int = BOOTSTRAP_REPLICATES,
                 seed: int = BOOTSTRAP_SEED) -> dict[str, Tensor]:
    """{fold: bootstrap weights (B, n_fold)} of each fold's test rows (its pattern groups ``groups[fold]``),
    drawn once and shared by every model, so that the replicates of two models are paired."""
    g = torch.Generator().manual_seed(seed)
    return {fold: group_weights(names, replicates, g) for fold, names in groups.items()}


def bootstrap_replicates(errors: Mapping[str, Sequence[Tensor]], weights: Mapping[str, Tensor],
                         name: str = "") -> Tensor:
    """Bootstrap replicates (B,) of a proxy (mean over folds of the mean over seeds of the offset-removed RMSE) from
    each fold's errors per seed [(n_fold, 3)] (any unit) and row weights (B, n_fold) (:func:`fold_weights`); each
    replicate also draws the seeds with replacement, from a generator seeded by ``name`` (independent of the others)."""
    g = torch.Generator().manual_seed(BOOTSTRAP_SEED + 1 + zlib.crc32(name.encode()))
    per_fold = []
    for fold, errs in errors.items():
        rmse = torch.stack([weighted_rmse(e.to(torch.float64), weights[fold]) for e in errs])     # (S, B)
        pick = torch.randint(len(errs), (rmse.shape[1], len(errs)), generator=g)              # (B, S)
        per_fold.append(rmse.T.gather(1, pick).mean(1))
    return torch.stack(per_fold).mean(0)


def proxy_scores(name: str, folds: dict[str, list[Fold]], seeds: Sequence[int]) -> dict:
    """{proxy: mean RMSE [mm], proxy + "_folds": {fold: RMSE averaged over seeds}, "seeds", "seconds"}
    for every proxy in ``folds``, fitted in this process (the benchmark spreads the fits over cores)."""
    start = time.perf_counter()
    seeds = model_seeds(name, seeds)
    rmse = {proxy: {f.name: [fold_rmse(name, f, s) for s in seeds] for f in fs} for proxy, fs in folds.items()}
    return summarize_scores(rmse, seeds, time.perf_counter() - start)


def choose_cc_variant(rec: Recording, spec: RobotSpec, smap: ServoMap,
                      variants: Sequence[str] = tuple(CC_VARIANTS)) -> tuple[str, dict[str, float]]:
    """(name, {variant: singles → pairs RMSE [mm] of the CC model alone}): the variant of :data:`CC_VARIANTS`
    with the lowest ``extrap`` score, ties to the earlier one (``base`` first). ValueError without families.
    """
    unknown = [v for v in variants if v not in CC_VARIANTS]
    if unknown or not variants:
        raise ValueError(f"cc variants: expected one or more of {tuple(CC_VARIANTS)}, got {list(variants)}")
    masks = proxy_masks(rec.labels, ("extrap",))["extrap"]
    scores = {v: round(float(np.mean([fold_rmse("cc", f, 0) for f in make_folds(rec, spec, smap, masks,
                                                                                   CC_VARIANTS[v])])), 4)
              for v in variants}
    return min(variants, key=lambda v: scores[v]), scores


def default_choice(scores: dict[str, dict], candidates: Sequence[str], proxy: str = SELECTION_PROXY,
                   replicates: Mapping[str, Tensor] | None = None, tie_sigmas: float = TIE_SIGMAS) -> dict:
    """The default model by the one-standard-error rule (docs/hardware.md), and why: ``best`` has the lowest
    ``proxy`` score; a candidate is *tied* with it when higher by at most ``tie_sigmas`` × the std of their paired
    bootstrapped difference (``replicates``: {model: (B,)} of :func:`bootstrap_replicates`); the default is the
    simplest tied candidate (:func:`~.registry.complexity`; equal ones: the earlier). Without ``replicates`` the
    lowest wins. Returns {"default", "best", "tied": [models], "rule", "reason", "candidates": {model: {"score_mm",
    "std_mm", "gap_mm", "gap_std_mm", "tied"}}} (std: of the model's own replicates).
    """
    scored = [c for c in candidates if c in scores and proxy in scores[c]]
    if not scored:
        raise ValueError(f"candidates: none of {list(candidates)} has a {proxy!r} score")
    if replicates is not None:
        missing = [c for c in scored if c not in replicates]
        if missing:
            raise ValueError(f"replicates: expected bootstrap replicates of every scored candidate, missing {missing}")
    best = min(scored, key=lambda c: (scores[c][proxy], complexity(c)))
    rows = {}
    for c in scored:
        gap = scores[c][proxy] - scores[best][proxy]
        spread = 0.0 if replicates is None else float((replicates[c] - replicates[best]).std())
        own = None if replicates is None else float(replicates[c].std())
        rows[c] = {"score_mm": round(float(scores[c][proxy]), 4), "std_mm": None if own is None else round(own, 4),
                   "gap_mm": round(float(gap), 4), "gap_std_mm": round(spread, 4),
                   "tied": bool(gap <= tie_sigmas * spread)}
    tied = [c for c in scored if rows[c]["tied"]]
    default = min(tied, key=lambda c: (complexity(c), scored.index(c)))
    if default == best and len(tied) == 1:
        reason = (f"{best} has the lowest {proxy} score ({rows[best]['score_mm']:.2f} mm) and beats every other "
                  f"candidate by more than {tie_sigmas:g}σ of the difference")
    else:
        others = ", ".join(f"{c} (+{rows[c]['gap_mm']:.2f} ± {rows[c]['gap_std_mm']:.2f})" for c in tied if c != best)
        reason = (f"{best} has the lowest {proxy} score ({rows[best]['score_mm']:.2f} mm); within {tie_sigmas:g}σ "
                  f"of the difference: {others}; the default is the simplest of them, {default}")
    return {"default": default, "best": best, "tied": tied, "candidates": rows, "reason": reason,
            "rule": f"one-standard-error: the simplest candidate whose {proxy} score is within {tie_sigmas:g}σ "
                    "(bootstrap over held-out pattern groups and proxy seeds, paired) of the lowest"}
