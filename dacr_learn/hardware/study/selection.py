"""Choosing a model on the training recording alone: two selection proxies and the default model.

Real validation patterns (all segments loaded at once) are absent from training recordings
(single segments and pairs), so a model must be chosen without them. Two train-only proxies,
both offset-removed tip RMSE [mm] on held-out rows of the training recording:

- ``cv``: leave-one-pattern-family-out cross-validation. Families (from the pattern labels):
  ``single`` (one segment or one tendon moved: ``seg<k>…``, ``tendon<k>…``) and one per pair of
  segments (``pair<jk>…``). Each fold holds one family out; the score is the mean over folds.
- ``extrap``: singles → pairs. Fit on the single-segment family, test on every pair family: a
  shift in the number of moving segments, like the one from training to validation.

In every fold the calibrated CC model is refitted on the fold's training rows, history inputs
run along the whole recording (causal), and each learned model is trained on the training rows
only. Labels without a family raise (there is no proxy without families).

The benchmark computes ``extrap`` by default (:data:`DEFAULT_PROXIES`, one fold per model) and the
family CV (four more folds on FTDCR v4/v6, ~4× the cost) on request; both are the same computation
whether or not the other is run.

Before the models, :func:`choose_cc_variant` picks the calibrated CC model's variant
(:data:`CC_VARIANTS`) by the CC model's own ``extrap`` score: the physical base of every
Clarke-space model is chosen per robot on the same proxy.

:func:`choose_default` picks the candidate with the lowest ``extrap`` (the proxy of the regime
shift; docs/hardware.md shows on FTDCR v4 how each proxy's ranking compares with val's).
"""
from __future__ import annotations

import re
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ...robot import RobotSpec
from ..ccmodel import CalibratedCC, fit_cc
from ..learned import Split, make_split
from ..metrics import offset_removed_rmse
from ..recording import Recording
from ..servo_map import ServoMap
from .registry import FitContext, build_model, model_info

CC_VARIANTS: dict[str, dict] = {"base": {}, "strain": {"pretension_strain": True}}   # name → CalibratedCC options
PROXIES = ("cv", "extrap")
SELECTION_PROXY = "extrap"
DEFAULT_PROXIES = (SELECTION_PROXY,)
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


def make_folds(rec: Recording, spec: RobotSpec, smap: ServoMap,
               masks: list[tuple[str, np.ndarray, np.ndarray]], cc_options: dict | None = None) -> list[Fold]:
    """Refit the calibrated CC model (``CalibratedCC(spec, **cc_options)``) on each fold's training rows
    and split the recording."""
    x = smap.displacements(spec, rec)
    folds = []
    for name, tr, te in masks:
        tr, te = torch.from_numpy(tr), torch.from_numpy(te)
        cc = CalibratedCC(spec, **(cc_options or {}))
        fit_cc(cc, x[tr], rec.tip[tr])
        for p in cc.parameters():
            p.requires_grad_(False)
        split = make_split(rec, spec, smap, cc)
        folds.append(Fold(name, FitContext(cc, smap, rec.servo_ids, split.rows(tr)), split.rows(te)))
    return folds


def fold_rmse(model_name: str, fold: Fold, seed: int) -> float:
    """Offset-removed RMSE [mm] of a model trained on the fold's rows, on its test rows."""
    model = build_model(model_name, fold.ctx, seed)
    model.fit(fold.ctx.train)
    with torch.no_grad():
        return float(offset_removed_rmse(model(fold.test), fold.test.tip)) * 1e3


def model_seeds(name: str, seeds: Sequence[int]) -> list[int]:
    """The seeds a model is fitted with: the first only for a deterministic model (the same for every seed)."""
    return list(seeds)[:1] if model_info(name).deterministic else list(seeds)


def summarize_scores(rmse: dict[str, dict[str, list[float]]], seeds: list[int], seconds: float) -> dict:
    """{proxy: mean over folds [mm], proxy + "_folds": {fold: mean over seeds}, "seeds", "seconds"} from
    {proxy: {fold: [RMSE [mm] per seed]}}."""
    out: dict = {}
    for proxy, folds in rmse.items():
        per = {fold: float(np.mean(values)) for fold, values in folds.items()}
        out[proxy] = round(float(np.mean(list(per.values()))), 4)
        out[proxy + "_folds"] = {k: round(v, 4) for k, v in per.items()}
    out["seeds"] = seeds
    out["seconds"] = round(seconds, 2)
    return out


def proxy_scores(name: str, folds: dict[str, list[Fold]], seeds: Sequence[int]) -> dict:
    """{proxy: mean RMSE [mm], proxy + "_folds": {fold: RMSE averaged over seeds}, "seeds", "seconds"}
    for every proxy in ``folds``, fitted in this process (the benchmark spreads the fits over cores)."""
    start = time.perf_counter()
    seeds = model_seeds(name, seeds)
    rmse = {proxy: {f.name: [fold_rmse(name, f, s) for s in seeds] for f in fs} for proxy, fs in folds.items()}
    return summarize_scores(rmse, seeds, time.perf_counter() - start)


def choose_cc_variant(rec: Recording, spec: RobotSpec, smap: ServoMap,
                      variants: Sequence[str] = tuple(CC_VARIANTS)) -> tuple[str, dict[str, float]]:
    """(name, {variant: singles → pairs RMSE [mm] of the CC model alone}): the calibrated CC variant of
    :data:`CC_VARIANTS` with the lowest ``extrap`` score, ties to the earlier one (``base`` first).

    The CC model is the physical base of every Clarke-space model, so its variant is chosen per robot
    before them, on the same train-only proxy (one CC fit per variant on the single-segment family).
    Raises ValueError when the labels name no pattern families."""
    unknown = [v for v in variants if v not in CC_VARIANTS]
    if unknown or not variants:
        raise ValueError(f"cc variants: expected one or more of {tuple(CC_VARIANTS)}, got {list(variants)}")
    masks = proxy_masks(rec.labels, ("extrap",))["extrap"]
    scores = {v: round(float(np.mean([fold_rmse("cc", f, 0) for f in make_folds(rec, spec, smap, masks,
                                                                                   CC_VARIANTS[v])])), 4)
              for v in variants}
    return min(variants, key=lambda v: scores[v]), scores


def choose_default(scores: dict[str, dict], candidates: Sequence[str], proxy: str = SELECTION_PROXY) -> str:
    """The candidate with the lowest ``proxy`` score (ties: the earlier candidate)."""
    scored = [c for c in candidates if c in scores and proxy in scores[c]]
    if not scored:
        raise ValueError(f"choose_default: none of the candidates {list(candidates)} has a {proxy!r} score")
    return min(scored, key=lambda c: scores[c][proxy])


def rank(values: dict[str, float]) -> list[str]:
    """Names sorted by value (lowest first)."""
    return sorted(values, key=values.get)
