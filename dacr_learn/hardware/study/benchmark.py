"""Benchmark of tip models on hardware recordings: calibrate, fit, select, train, evaluate, report.

Steps (file names from arguments, servo ids from the CSV header):

1. Robot + servo map: ``servo_maps/<robot file name>`` next to the robot YAML (or ``--servo-map``); without
   one, calibrate from ``--pulls`` and write ``calibrated_robot.yaml`` and its servo map into the run folder.
2. Choose the CC variant (:func:`.selection.choose_cc_variant`) and fit the CC model on the training recording.
3. Score every model with the train-only proxies (:mod:`.selection`) and choose the default model.
4. Train every model of :mod:`.registry` (learned ones once per seed) on the training recording and evaluate
   on the validation recording when there is one (offset-removed RMSE, mean and p95 error).

Steps 3 and 4 are independent fits: ``submit_*`` hands them to a :class:`.pool.TaskPool`, ``collect_*``
assembles the results in model order, ``run_*`` do both. ``instant`` models run in this process.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ...robot import RobotSpec
from ..calibration import calibrate, default_map_path, write_calibration
from ..ccmodel import CalibratedCC, fit_cc
from ..cosserat_learned import warmups
from ..deploy.checkpoint import HardwareModel
from ..deploy.uncertainty import SigmaCalibration, SupportModel
from ..learned import Split, cc_as_residual, make_split
from ..metrics import offset_removed_rmse, tip_metrics
from ..recording import Recording, load_recording
from ..servo_map import ServoMap
from . import selection
from .pool import TaskPool
from .registry import FitContext, build_model, model_info
from .selection import Fold, model_seeds


@dataclass
class Setup:
    """Everything the models need: robot, servo map, fitted CC model and the splits (val optional)."""

    spec: RobotSpec
    smap: ServoMap
    cc: CalibratedCC
    train_rec: Recording
    val_rec: Recording | None
    train: Split
    val: Split | None
    calibration: dict
    cc_fit: dict
    cc_options: dict = field(default_factory=dict)   # CalibratedCC options of the chosen CC variant
    cache_dir: Path | None = None                     # where worker processes share Cosserat calibrations, or None

    def context(self) -> FitContext:
        return FitContext(self.cc, self.smap, self.train_rec.servo_ids, self.train, self.cache_dir)


def resolve_robot(robot: Path, servo_map: Path | None, pulls: Path | None, out: Path,
                  units: str) -> tuple[RobotSpec, ServoMap, dict]:
    """Robot + servo map from files, or calibrated from ``pulls`` (written into ``out``)."""
    spec = RobotSpec.from_yaml(robot)
    path = servo_map or default_map_path(robot)
    if path.exists():
        smap = ServoMap.from_yaml(path)
        return spec, smap, {"servo_map": str(path), **smap.calibration}
    if pulls is None or not pulls.exists():
        raise ValueError(f"no servo map for {robot} (looked for {path}) and no single-pull recording "
                         f"to calibrate from (--pulls {pulls})")
    spec, smap, report = calibrate(load_recording(pulls, spec, units), spec)
    robot_out = out / "calibrated_robot.yaml"
    map_out = default_map_path(robot_out)
    write_calibration(spec, smap, robot_out, map_out)
    return spec, smap, {"servo_map": str(map_out), "robot": str(robot_out), **report}


def load_setup(robot: Path, train: Path, val: Path | None, out: Path, servo_map: Path | None = None,
               pulls: Path | None = None, units: str = "mm", cc_variant: str = "base") -> Setup:
    """Robot, servo map, recordings and the CC model fitted on ``train``; ``val`` may be None. ``cc_variant``: a name
    of :data:`.selection.CC_VARIANTS` or ``"auto"`` (:func:`.selection.choose_cc_variant`; ``base`` without pattern
    families), recorded in ``cc_fit["variant"]``."""
    spec, smap, cal = resolve_robot(robot, servo_map, pulls, out, units)
    train_rec = load_recording(train, spec, units)
    val_rec = load_recording(val, spec, units) if val is not None else None
    smap.check(spec, train_rec.servo_ids)
    variant = _cc_variant(cc_variant, train_rec, spec, smap)
    cc = CalibratedCC(spec, **selection.CC_VARIANTS[variant["chosen"]])
    fit = fit_cc(cc, smap.displacements(spec, train_rec), train_rec.tip)
    fit["parameters"], fit["variant"] = cc.report(), variant
    cc.requires_grad_(False)
    val_split = make_split(val_rec, spec, smap, cc) if val_rec is not None else None
    return Setup(spec, smap, cc, train_rec, val_rec, make_split(train_rec, spec, smap, cc), val_split, cal, fit,
                 dict(selection.CC_VARIANTS[variant["chosen"]]))


def _cc_variant(requested: str, rec: Recording, spec: RobotSpec, smap: ServoMap) -> dict:
    """{"requested", "chosen", "extrap": {variant: CC singles → pairs [mm]} (auto only)}."""
    if requested != "auto":
        if requested not in selection.CC_VARIANTS:
            raise ValueError(f"cc_variant: expected 'auto' or one of {tuple(selection.CC_VARIANTS)}, got {requested!r}")
        return {"requested": requested, "chosen": requested}
    try:
        chosen, scores = selection.choose_cc_variant(rec, spec, smap)
    except ValueError as err:                      # no pattern families: no proxy to choose with
        print(f"cc variant: no singles → pairs proxy ({err}); using 'base'")
        return {"requested": "auto", "chosen": "base"}
    return {"requested": "auto", "chosen": chosen, "extrap": scores}


def fit_model(name: str, s: Setup, seed: int = 0) -> nn.Module:
    """Model ``name`` trained on the whole training recording (e.g. the default model, to save)."""
    model = build_model(name, s.context(), seed)
    model.fit(s.train)
    return model


def _summary(values: list[float]) -> dict:
    a = np.asarray(values)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
            "per_seed": [round(float(v), 4) for v in a]}


def run_seed(name: str, s: Setup, seed: int, keep: bool = False) -> tuple[dict, torch.Tensor | None, nn.Module | None]:
    """One training run: ({"train": metrics, "val": metrics (with val)}, val predictions or None, the fitted
    model if ``keep`` else None — e.g. the members ``--save`` bundles, returned instead of trained again)."""
    model = fit_model(name, s, seed)
    with torch.no_grad():
        run, pred_val = {"train": tip_metrics(model(s.train), s.train.tip)}, None
        if hasattr(model, "physics_report"):          # a physical model's calibrated parameters (Cosserat)
            run["physics"] = model.physics_report()
        if s.val is not None:
            pred_val = model(s.val)
            run["val"] = tip_metrics(pred_val, s.val.tip)
    return run, pred_val, model.eval() if keep else None


def _submit(pool: TaskPool, name: str, fn: Callable, *args) -> Future:
    """Models fitted in no time (``instant``: the linear map, the CC model) in this process; the others (learned
    ones, the Cosserat calibration) to the pool."""
    return (pool.run_here if model_info(name).instant else pool.submit)(fn, name, *args)


def submit_benchmark(pool: TaskPool, s: Setup, models: Sequence[str], seeds: Sequence[int],
                     keep: Sequence[str] = ()) -> dict[str, list]:
    """{model: [future of timed(run_seed) per seed]}: every model trained on the whole training recording;
    the fitted models of those in ``keep`` come back with their results (:func:`collect_benchmark`)."""
    return {name: [_submit(pool, name, run_seed, s, seed, name in keep) for seed in model_seeds(name, seeds)]
            for name in models}


def summarize_model(name: str, runs: list[tuple[tuple, float]], seeds: list[int]) -> tuple[dict, torch.Tensor | None]:
    """(summary over seeds, val predictions of the first seed or None) from [((run, pred, model), seconds)]."""
    info = model_info(name)
    summary = {"clarke_space": info.clarke_space, "static": info.static,
               "seeds": seeds[:len(runs)], "seconds_per_run": float(np.mean([sec for _, sec in runs]))}
    first = runs[0][0][0]
    for split in ("val", "train"):
        if split in first:
            summary[split] = {k: _summary([run[0][split][k] for run, _ in runs]) for k in first[split]}
    if "physics" in first:
        summary["physics"] = first["physics"]
    return summary, runs[0][0][1]


progress = partial(print, flush=True)   # a line shows at once even when stdout is a file or pipe (block-buffered)


def _elapsed(start: float | None) -> str:
    """", N s elapsed" since ``start`` (a perf_counter reading) for a progress line; "" without one."""
    return "" if start is None else f", {time.perf_counter() - start:.0f} s elapsed"


def collect_benchmark(pending: dict[str, list], seeds: Sequence[int], log: Callable = progress,
                      fitted: dict[str, list[nn.Module]] | None = None,
                      start: float | None = None) -> tuple[dict, dict[str, torch.Tensor]]:
    """({model: summary}, {model: val predictions (first seed)}; empty without val), logged in model order as each
    model's runs finish (with the time since ``start``).
    ``fitted``: a dict that receives {model: [fitted model per seed]} of the models submitted with ``keep``."""
    results, preds = {}, {}
    for k, (name, futures) in enumerate(pending.items()):
        runs = [f.result() for f in futures]
        results[name], pred = summarize_model(name, runs, list(seeds))
        if pred is not None:
            preds[name] = pred
        if fitted is not None and runs[0][0][2] is not None:
            fitted[name] = [run[2] for run, _ in runs]
        r = results[name]
        v = r.get("val")
        shown = (f"val RMSE {v['rmse_mm']['mean']:6.2f} ± {v['rmse_mm']['std']:.2f} mm  "
                 f"mean {v['mean_mm']['mean']:6.2f}  p95 {v['p95_mm']['mean']:6.2f}  " if v else "")
        log(f"[final {k + 1}/{len(pending)}] {name:36s} {shown}(train {r['train']['rmse_mm']['mean']:.2f}, "
            f"{r['seconds_per_run']:.1f} s/run{_elapsed(start)})")
    return results, preds


@dataclass
class PendingSelection:
    """The proxy fits handed to a pool: {model: {proxy: {fold: [future of timed(fold_predictions) per seed]}}},
    the folds per proxy and the seeds per model."""

    fits: dict[str, dict[str, dict[str, list[Future]]]]
    folds: dict[str, list[Fold]]
    seeds: dict[str, list[int]]


@dataclass
class SelectionResult:
    """The train-only proxies of every model: ``scores`` ({model: :func:`.selection.summarize_scores`}, what
    results.json records), ``replicates`` ({model: {proxy: bootstrap replicates (B,) [mm]}}), the held-out
    ``predictions`` ({model: {proxy: {fold: [tips (n_fold, 3) [m] per seed]}}}) and the ``folds``."""

    scores: dict
    replicates: dict[str, dict[str, torch.Tensor]]
    predictions: dict
    folds: dict[str, list[Fold]]
    seeds: dict[str, list[int]]


def submit_warmups(pool: TaskPool, fits: Sequence[tuple[FitContext, str, Sequence[int]]],
                   log: Callable | None = None, start: float | None = None) -> list[Future]:
    """Hand each shared piece the fits [(context, model, seeds)] need (Cosserat calibrations, then their synthetic
    tips: :func:`..cosserat_learned.warmups`) to the pool once, ahead of the fits (nothing with ``jobs=1``: the fits
    compute them when first asked). ``log``: called with a line as each piece finishes.
    """
    if pool.jobs == 1:
        return []
    pieces: dict[str, tuple] = {}
    for ctx, name, seeds in fits:
        for seed in model_seeds(name, seeds):
            for key, fn, args in warmups(build_model(name, ctx, seed), ctx.train):
                pieces.setdefault(key, (fn, args))
    order = sorted(pieces, key=lambda k: "synthetic" in k)          # every calibration before the synthetic tips
    futures = [pool.submit(pieces[k][0], *pieces[k][1]) for k in order]
    if log is not None:
        done = iter(range(1, len(futures) + 1))                        # next() is atomic: callbacks may race

        def report(future: Future, what: str) -> None:
            if future.exception() is None:
                log(f"[shared {next(done)}/{len(futures)}] {what} ready ({future.result()[1]:.0f} s{_elapsed(start)})")

        for key, future in zip(order, futures, strict=True):
            what = "Cosserat synthetic tips" if "synthetic" in key else "Cosserat calibration"
            future.add_done_callback(lambda f, what=what: report(f, what))
    return futures


def selection_folds(s: Setup, proxies: Sequence[str] = selection.DEFAULT_PROXIES) -> dict[str, list[Fold]]:
    """{proxy: folds} of the training recording (CC refitted per fold). Raises ValueError when the labels name
    no pattern families (:func:`.selection.proxy_masks`)."""
    return {proxy: selection.make_folds(s.train_rec, s.spec, s.smap, m, s.cc_options, s.cache_dir)
            for proxy, m in selection.proxy_masks(s.train_rec.labels, proxies).items()}


def proxy_seeds_of(models: Sequence[str], seeds: Sequence[int], all_seeds: Sequence[str] | None = None
                   ) -> dict[str, list[int]]:
    """{model: its proxy seeds}: every seed for the models in ``all_seeds`` (default: all), the first for the
    others; one for a deterministic model."""
    full = set(models if all_seeds is None else all_seeds)
    return {name: model_seeds(name, seeds if name in full else list(seeds)[:1]) for name in models}


def submit_selection(pool: TaskPool, s: Setup, models: Sequence[str], seeds: Sequence[int],
                     proxies: Sequence[str] = selection.DEFAULT_PROXIES, all_seeds: Sequence[str] | None = None,
                     folds: dict[str, list[Fold]] | None = None) -> PendingSelection:
    """Every model's proxy fits handed to ``pool`` on ``folds`` (default: :func:`selection_folds`). The models in
    ``all_seeds`` (default: every model) are fitted with every seed, the others (scored for comparison) with
    the first (:func:`proxy_seeds_of`). Raises ValueError when the labels name no pattern families."""
    folds = selection_folds(s, proxies) if folds is None else folds
    per_model = proxy_seeds_of(models, seeds, all_seeds)
    predict = selection.fold_predictions
    fits = {name: {proxy: {f.name: [_submit(pool, name, predict, f, seed) for seed in per_model[name]]
                           for f in fs} for proxy, fs in folds.items()} for name in models}
    return PendingSelection(fits, folds, per_model)


_PROXY_NAMES = {"cv": "family CV", "extrap": "singles→pairs"}


def collect_selection(pending: PendingSelection, log: Callable = progress,
                      start: float | None = None) -> SelectionResult:
    """Every model's train-only proxy scores with their uncertainty (:func:`.selection.summarize_scores`,
    bootstrap over the held-out pattern groups and the seeds, :func:`.selection.bootstrap_replicates`; seconds:
    the model's fits), logged per model as its fits finish (with the time since ``start``)."""
    weights = {proxy: selection.fold_weights({f.name: f.groups for f in fs}) for proxy, fs in pending.folds.items()}
    tips = {proxy: {f.name: f.test.tip for f in fs} for proxy, fs in pending.folds.items()}
    scores, replicates, predictions = {}, {}, {}
    for k, (name, per) in enumerate(pending.fits.items()):
        done = {proxy: {fold: [f.result() for f in fs] for fold, fs in folds.items()} for proxy, folds in per.items()}
        predictions[name] = {proxy: {fold: [p for p, _ in runs] for fold, runs in folds.items()}
                             for proxy, folds in done.items()}
        errors = {proxy: {fold: [1e3 * (p - tips[proxy][fold]) for p in preds] for fold, preds in folds.items()}
                  for proxy, folds in predictions[name].items()}
        rmse = {proxy: {fold: [float(offset_removed_rmse(e, torch.zeros_like(e))) for e in errs]
                        for fold, errs in folds.items()} for proxy, folds in errors.items()}
        replicates[name] = {proxy: selection.bootstrap_replicates(errors[proxy], weights[proxy], name)
                            for proxy in errors}
        seconds = sum(sec for folds in done.values() for runs in folds.values() for _, sec in runs)
        scores[name] = p = selection.summarize_scores(rmse, pending.seeds[name], seconds, replicates[name])
        shown = ", ".join(f"{_PROXY_NAMES[proxy]} {p[proxy]:6.2f} ± {p[proxy + '_std']:.2f} mm" for proxy in per)
        log(f"[proxy {k + 1}/{len(pending.fits)}] {name:36s} {shown} ({len(pending.seeds[name])} seed(s), "
            f"{p['seconds']:.0f} s of fits{_elapsed(start)})")
    return SelectionResult(scores, replicates, predictions, pending.folds, pending.seeds)


def default_candidates(models: Sequence[str], deployable_only: bool = True) -> tuple[str, ...]:
    """The models the default is chosen from: the Clarke-space ones that ``--save`` and the export can
    deploy (``deployable_only=False``: every Clarke-space model, to report which one the proxy prefers)."""
    return tuple(m for m in models if model_info(m).clarke_space and (model_info(m).deployable or not deployable_only))


def select_default(scores: dict, replicates: dict | None = None) -> dict:
    """The default model among :func:`default_candidates` and why (:func:`.selection.default_choice`, on the
    selection proxy's bootstrap ``replicates`` {model: {proxy: (B,)}} when given)."""
    reps = None if replicates is None else {m: r[selection.SELECTION_PROXY] for m, r in replicates.items()}
    return selection.default_choice(scores, default_candidates(list(scores)), selection.SELECTION_PROXY, reps)


def fit_hardware_model(setup, name: str, seeds: list[int], sigma: SigmaCalibration | None = None,
                       info: dict | None = None, members: list[nn.Module] | None = None) -> HardwareModel:
    """Train model ``name`` (a CC Clarke-residual model, the compositional CC model, or ``cc``) once per seed on the
    training recording and bundle the ensemble with the support model of the training commands and, if given, a
    σ calibration. ``members``: models already fitted that way, one per seed, bundled instead (ignored for ``cc``).
    """
    if name == "cc":                    # deterministic: one member, the CC model itself
        members = [cc_as_residual(setup.train, setup.cc)]
    elif members is not None:
        if len(members) != len(seeds):
            raise ValueError(f"members: expected one fitted {name} per seed {list(seeds)}, got {len(members)}")
        members = [m.eval() for m in members]
    else:
        members = [fit_model(name, setup, seed).eval() for seed in seeds]
    support = SupportModel(setup.spec.num_segments).fit(setup.train.features[..., :2], list(setup.train_rec.labels))
    servo = 1e3 * setup.train_rec.servo                                            # [mm]
    recorded = {"lower": servo.amin(0).tolist(), "upper": servo.amax(0).tolist()}   # the IK's box (HardwareTip)
    return HardwareModel(name, setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc, members,
                         sigma=sigma, support=support, examples=servo[:256],
                         info={**dict(info or {}), "servo_range_mm": recorded})
