"""Benchmark of tip models on hardware recordings: calibrate, fit, train, evaluate, report.

Steps (all generic: file names come from arguments, servo ids from the CSV header):

1. Robot + servo map: the robot YAML's servo map (``servo_maps/<robot file name>`` next to
   it, or ``--servo-map``); without one, calibrate from the single-pull recording ``--pulls``
   and write ``calibrated_robot.yaml`` / ``servo_maps/calibrated_robot.yaml`` into the run folder.
2. Fit the calibrated CC model's physical parameters on the training recording.
3. Train every model of :mod:`dacr_learn.hardware.learned` (learned ones once per seed) and
   evaluate on the validation recording: offset-removed RMSE, mean and p95 Euclidean error.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..robot import RobotSpec
from .calibration import calibrate, default_map_path, write_calibration
from .ccmodel import CalibratedCC, fit_cc
from .learned import (
    PRETRAIN_SAMPLES,
    CCClarkeResidual,
    CCClarkeResidualHistory,
    CCOnly,
    CCTipResidual,
    LinearRaw,
    Pretrained,
    Split,
    TipMLP,
    make_split,
    synthetic_split,
)
from .metrics import tip_metrics
from .recording import Recording, load_recording
from .servo_map import ServoMap

MODELS = ("linear_raw", "mlp_raw", "mlp_clarke", "cc", "cc_tip_residual", "cc_clarke_residual",
          "pretrained_clarke", "pretrained_raw", "cc_clarke_residual_history")
DETERMINISTIC = ("linear_raw", "cc")
CLARKE_MODELS = ("mlp_clarke", "cc", "cc_tip_residual", "cc_clarke_residual", "pretrained_clarke",
                 "cc_clarke_residual_history")
STATIC_MODELS = MODELS[:-1]  # all but the history model map one command to one tip
LETTERS = {"linear_raw": "a", "mlp_raw": "b", "mlp_clarke": "c", "cc": "d", "cc_tip_residual": "e",
           "cc_clarke_residual": "e", "pretrained_clarke": "f", "pretrained_raw": "f",
           "cc_clarke_residual_history": "g"}


@dataclass
class Setup:
    """Everything the models need: robot, servo map, fitted CC model and the two splits."""

    spec: RobotSpec
    smap: ServoMap
    cc: CalibratedCC
    train_rec: Recording
    val_rec: Recording
    train: Split
    val: Split
    calibration: dict
    cc_fit: dict


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


def load_setup(robot: Path, train: Path, val: Path, out: Path, servo_map: Path | None = None,
               pulls: Path | None = None, units: str = "mm") -> Setup:
    spec, smap, cal = resolve_robot(robot, servo_map, pulls, out, units)
    train_rec, val_rec = load_recording(train, spec, units), load_recording(val, spec, units)
    smap.check(spec, train_rec.servo_ids)
    cc = CalibratedCC(spec)
    x_train = smap.displacements(spec, train_rec)
    fit = fit_cc(cc, x_train, train_rec.tip)
    fit["parameters"] = cc.report()
    for p in cc.parameters():
        p.requires_grad_(False)
    return Setup(spec, smap, cc, train_rec, val_rec, make_split(train_rec, spec, smap, cc),
                 make_split(val_rec, spec, smap, cc), cal, fit)


def build(name: str, s: Setup, seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    if name == "linear_raw":
        return LinearRaw()
    if name == "cc":
        return CCOnly()
    if name in ("mlp_raw", "mlp_clarke"):
        return TipMLP(name.split("_")[1], s.train)
    if name == "cc_tip_residual":
        return CCTipResidual(s.train)
    if name == "cc_clarke_residual":
        return CCClarkeResidual(s.train, s.cc)
    if name == "cc_clarke_residual_history":
        return CCClarkeResidualHistory(s.train, s.cc)
    if name in ("pretrained_clarke", "pretrained_raw"):
        synth = synthetic_split(s.cc, s.smap, s.train_rec.servo_ids, PRETRAIN_SAMPLES, seed=1000 + seed)
        return Pretrained(name.split("_")[1], s.train, synth)
    raise ValueError(f"model: got {name!r}, expected one of {MODELS}")


def _summary(values: list[float]) -> dict:
    a = np.asarray(values)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
            "per_seed": [round(float(v), 4) for v in a]}


def run_model(name: str, s: Setup, seeds: list[int]) -> tuple[dict, torch.Tensor]:
    """Train/evaluate one model over seeds; returns (summary, val predictions of the first seed)."""
    runs, first_pred = [], None
    for seed in (seeds[:1] if name in DETERMINISTIC else seeds):
        start = time.perf_counter()
        model = build(name, s, seed)
        model.fit(s.train)
        with torch.no_grad():
            pred_val, pred_train = model(s.val), model(s.train)
        runs.append({"val": tip_metrics(pred_val, s.val.tip), "train": tip_metrics(pred_train, s.train.tip),
                     "seconds": time.perf_counter() - start})
        first_pred = pred_val if first_pred is None else first_pred
    summary = {"letter": LETTERS[name], "clarke_space": name in CLARKE_MODELS, "static": name in STATIC_MODELS,
               "seeds": seeds[:len(runs)], "seconds_per_run": float(np.mean([r["seconds"] for r in runs]))}
    for split in ("val", "train"):
        summary[split] = {k: _summary([r[split][k] for r in runs]) for k in runs[0][split]}
    return summary, first_pred


def run_benchmark(s: Setup, models: tuple[str, ...] = MODELS, seeds: tuple[int, ...] = (0, 1, 2),
                  log=print) -> tuple[dict, dict[str, torch.Tensor]]:
    """All models → ({model: summary}, {model: val predictions (first seed)})."""
    results, preds = {}, {}
    for name in models:
        results[name], preds[name] = run_model(name, s, list(seeds))
        v = results[name]["val"]
        log(f"{name:20s} val RMSE {v['rmse_mm']['mean']:6.2f} ± {v['rmse_mm']['std']:.2f} mm  "
            f"mean {v['mean_mm']['mean']:6.2f}  p95 {v['p95_mm']['mean']:6.2f}  "
            f"(train {results[name]['train']['rmse_mm']['mean']:.2f}, {results[name]['seconds_per_run']:.1f} s/run)")
    return results, preds


def markdown_table(results: dict) -> str:
    """Results table (val metrics, mean ± std over seeds) in Markdown."""
    lines = ["| | model | inputs | val RMSE, offset removed [mm] | val mean [mm] | val p95 [mm] | train RMSE [mm] | seeds |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        v, t = r["val"], r["train"]
        pm = lambda d: f"{d['mean']:.2f} ± {d['std']:.2f}" if len(d["per_seed"]) > 1 else f"{d['mean']:.2f}"  # noqa: E731
        inputs = ("Clarke" if r["clarke_space"] else "raw servo") + ("" if r["static"] else " + history")
        lines.append(f"| {r['letter']} | `{name}` | {inputs} | {pm(v['rmse_mm'])} | {pm(v['mean_mm'])} | {pm(v['p95_mm'])} | "
                     f"{pm(t['rmse_mm'])} | {len(r['seeds'])} |")
    return "\n".join(lines)
