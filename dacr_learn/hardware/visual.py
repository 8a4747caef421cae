"""Figures and Rerun recordings of predicted vs measured tip paths on a validation recording."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .benchmark import Setup
from .metrics import offset_removed_errors
from .registry import MODELS

COLORS = {"measured": (20, 20, 20), "cc": (31, 119, 180)}
PALETTE = [(214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (255, 0, 255), (0, 150, 136)]
# one colour per registered model besides cc: k = 1 … 11 in registry order never wraps onto another's


def _color(name: str, k: int) -> tuple[int, int, int]:
    """A model's colour: fixed by its registry position (so the PNG, which shows a few models, and the
    Rerun recording, which shows all, agree); ``k`` (its position in the plot) only for other names."""
    if name in MODELS:
        k = MODELS.index(name) + 1
    return COLORS.get(name, PALETTE[k % len(PALETTE)])


def label_runs(labels: tuple[str, ...]) -> list[slice]:
    """Consecutive rows with the same label (ignoring a trailing '_hold'), as slices."""
    base = [lab.removesuffix("_hold") for lab in labels]
    runs, start = [], 0
    for i in range(1, len(base) + 1):
        if i == len(base) or base[i] != base[start]:
            runs.append(slice(start, i))
            start = i
    return runs


def centered_errors_mm(pred: torch.Tensor, meas: torch.Tensor) -> np.ndarray:
    """‖e_k − ē‖ per row [mm] (the terms of the offset-removed RMSE)."""
    return (offset_removed_errors(pred.double(), meas.double()) * 1e3).numpy()


def plot_paths(setup: Setup, preds: dict[str, torch.Tensor], path: Path) -> None:
    """PNG: top (x–y) and side (x–z) views of the val tip paths, and the error per sample."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meas = setup.val.tip.numpy() * 1e3
    runs = label_runs(setup.val_rec.labels)
    fig, axes = plt.subplots(1, 3, figsize=(18, 6), gridspec_kw={"width_ratios": [1, 1, 1.3]})
    series = {"measured": meas} | {k: v.numpy() * 1e3 for k, v in preds.items()}
    for k, (name, pts) in enumerate(series.items()):
        color = np.array(_color(name, k)) / 255
        for r_i, r in enumerate(runs):
            kw = dict(color=color, lw=1.6 if name == "measured" else 1.0, alpha=0.9,
                      label=name if r_i == 0 else None, ls="-" if name == "measured" else "--")
            axes[0].plot(pts[r, 0], pts[r, 1], **kw)
            axes[1].plot(pts[r, 0], pts[r, 2], **kw)
    for ax, (a, b) in zip(axes[:2], [("x", "y"), ("x", "z")], strict=True):
        ax.set_xlabel(f"{a} [mm]"), ax.set_ylabel(f"{b} [mm]"), ax.set_aspect("equal"), ax.grid(alpha=0.3)
    axes[0].set_title("top view"), axes[1].set_title("side view"), axes[0].legend(loc="best", fontsize=8)
    for k, (name, pred) in enumerate(preds.items(), start=1):
        err = centered_errors_mm(pred, setup.val.tip)
        rmse = float(np.sqrt((err**2).mean()))
        axes[2].plot(err, color=np.array(_color(name, k)) / 255, lw=1, label=f"{name} (RMSE {rmse:.2f} mm)")
    for r in runs:
        axes[2].axvline(r.start, color="0.85", lw=0.5)
    axes[2].set_xlabel("val sample (grey lines: pattern starts)"), axes[2].set_ylabel("offset-removed error [mm]")
    axes[2].legend(fontsize=8), axes[2].grid(alpha=0.3)
    fig.suptitle(f"{setup.spec.name}: predicted vs measured tip paths on {Path(setup.val_rec.source).name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


RERUN_MEASURED = (235, 235, 235)   # the viewer's background is dark: measured path in white there
SAMPLE_TIMELINE = "sample"


def _rerun_color(name: str, k: int) -> tuple[int, int, int]:
    return RERUN_MEASURED if name == "measured" else _color(name, k)


def error_axis_max(errors: dict[str, np.ndarray]) -> float:
    """Top of the error plot [mm]: 1.3 × the largest p95 error of the models within 2× of the best
    RMSE, so that a poor model's spikes do not flatten the others (its RMSE stays in the legend)."""
    rmse = {name: float(np.sqrt((e**2).mean())) for name, e in errors.items()}
    p95 = {name: float(np.percentile(e, 95)) for name, e in errors.items()}
    best = min(rmse.values())
    top = 1.3 * max(p95[n] for n, r in rmse.items() if r <= 2 * best)
    return top if top > 0 else 1.3 * max(p95.values()) or 1.0  # a perfect model must not collapse the axis


def hardware_blueprint(errors: dict[str, np.ndarray], with_std: bool, shown_3d: int = 3):
    """Layout for :func:`log_rerun`; ``errors``: model -> offset-removed errors [mm].

    A large 3D view (measured path, the CC model, the ``shown_3d`` lowest-RMSE models and their
    ±2σ bands; the other models are hidden there, one click away in the blueprint panel) beside
    one error plot with every model overlaid (one y-scale from 0 to :func:`error_axis_max`,
    legend with RMSEs), the predicted-2σ plot when given, and the RMSE table. Opens at the
    last sample (follow mode).
    """
    import rerun.blueprint as rrb
    from rerun.blueprint.components import PlayState

    whole = rrb.VisibleTimeRange(SAMPLE_TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.infinite())
    everything = rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    common = dict(time_ranges=[whole], axis_x=rrb.TimeAxis(view_range=everything),  # every sample, not a window
                  plot_legend=rrb.PlotLegend(rrb.Corner2D.RightTop, visible=True))
    top = error_axis_max(errors)
    plots = [rrb.TimeSeriesView(origin="errors", axis_y=rrb.ScalarAxis(range=(0.0, top)), **common,
                                name=f"offset-removed tip error [mm], all {len(errors)} models (y 0–{top:.0f} mm)")]
    if with_std:
        plots.append(rrb.TimeSeriesView(origin="sigma", name="predicted 2σ [mm] (uncertainty)", **common))
    side = rrb.Vertical(*plots, rrb.TextDocumentView(origin="summary", name="val RMSE"),
                        row_shares=[3] * len(plots) + [2])
    ranked = sorted(errors, key=lambda n: float((errors[n] ** 2).mean()))
    hidden = [n for n in ranked[shown_3d:] if n != "cc"]
    behaviour = [rrb.EntityBehavior(visible=False)]
    overrides = {f"world/{kind}/{n}": behaviour for n in hidden for kind in ("paths", "tip", "band_2sigma")}
    shown = ", ".join(n for n in ranked if n not in hidden)
    scene = rrb.Spatial3DView(origin="world", overrides=overrides,
                              name=f"val tip paths: measured (white) and {shown}; CC backbone (blue)")
    time_panel = rrb.TimePanel(timeline=SAMPLE_TIMELINE, play_state=PlayState.Following, state="collapsed")
    return rrb.Blueprint(rrb.Horizontal(scene, side, column_shares=[3, 2]), time_panel, collapse_panels=True)


def _check_std(std: dict[str, torch.Tensor] | None, preds: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """σ per model as ``(N, 3)`` metres (an ``(N,)`` σ is isotropic); ValueError on unknown models or shapes."""
    out = {}
    for name, sd in (std or {}).items():
        if name not in preds:
            raise ValueError(f"std given for {name!r}, which has no predictions (models: {sorted(preds)})")
        arr = np.asarray(sd.detach().cpu() if isinstance(sd, torch.Tensor) else sd, dtype=np.float32)
        n = preds[name].shape[0]
        if arr.shape == (n,):
            arr = np.repeat(arr[:, None], 3, axis=1)
        if arr.shape != (n, 3) or not np.isfinite(arr).all() or (arr < 0).any():
            raise ValueError(f"std[{name!r}] must be finite, >= 0, shape ({n},) or ({n}, 3) [m]; got {arr.shape}")
        out[name] = arr
    return out


def _log_paths(rec, setup: Setup, preds: dict[str, torch.Tensor], sigma: dict[str, np.ndarray]) -> None:
    """Static: every path as line strips (one per pattern run) and the ±2σ band around predicted ones."""
    import rerun as rr

    runs = label_runs(setup.val_rec.labels)
    series = {"measured": setup.val.tip} | preds
    for k, (name, pts) in enumerate(series.items()):
        strips = [pts[r].numpy() for r in runs]
        width = 0.0007 if name == "measured" else 0.0004
        paths = rr.LineStrips3D(strips, colors=[_rerun_color(name, k)], radii=width)
        rec.log(f"world/paths/{name}", paths, static=True)
        if name in sigma:
            band = rr.Ellipsoids3D(centers=pts.numpy(), half_sizes=2 * sigma[name], colors=[(*_color(name, k), 30)],
                                   fill_mode=rr.components.FillMode.Solid)
            rec.log(f"world/band_2sigma/{name}", band, static=True)


def _log_samples(rec, setup: Setup, preds: dict[str, torch.Tensor], errors: dict[str, np.ndarray],
                 sigma: dict[str, np.ndarray]) -> dict[str, float]:
    """Per sample (batched columns): tips, CC backbone, each model's error and 2σ [mm]; returns RMSEs [mm]."""
    import rerun as rr

    n = len(setup.val.tip)
    index = [rr.TimeColumn(SAMPLE_TIMELINE, sequence=np.arange(n))]
    labels = list(setup.val_rec.labels)
    rec.log("world/tip/measured", rr.Points3D.from_fields(colors=[RERUN_MEASURED], radii=0.002), static=True)
    rec.send_columns("world/tip/measured", index, rr.Points3D.columns(positions=setup.val.tip.numpy(), labels=labels))
    with torch.no_grad():
        backbone = setup.cc.backbone(setup.val.x).numpy()
    rec.log("world/robot/cc_backbone", rr.LineStrips3D.from_fields(colors=[COLORS["cc"]], radii=0.001), static=True)
    rec.send_columns("world/robot/cc_backbone", index, rr.LineStrips3D.columns(strips=backbone))
    rmse = {}
    for k, (name, pred) in enumerate(preds.items(), start=1):
        color, err = _color(name, k), errors[name]
        rmse[name] = float(np.sqrt((err**2).mean()))
        rec.log(f"world/tip/{name}", rr.Points3D.from_fields(colors=[color], radii=0.0015), static=True)
        rec.send_columns(f"world/tip/{name}", index, rr.Points3D.columns(positions=pred.numpy()))
        rec.log(f"errors/{name}", rr.SeriesLines(names=[f"{name} ({rmse[name]:.2f} mm)"], colors=[color]), static=True)
        rec.send_columns(f"errors/{name}", index, rr.Scalars.columns(scalars=err))
        if name in sigma:
            two_sigma_mm = 2e3 * np.linalg.norm(sigma[name], axis=1)
            rec.log(f"sigma/{name}", rr.SeriesLines(names=[f"{name} 2σ"], colors=[color]), static=True)
            rec.send_columns(f"sigma/{name}", index, rr.Scalars.columns(scalars=two_sigma_mm))
    return rmse


def _summary(setup: Setup, rmse: dict[str, float]) -> str:
    rows = "\n".join(f"| {name} | {value:.2f} |" for name, value in sorted(rmse.items(), key=lambda kv: kv[1]))
    return (f"**{setup.spec.name}**, {len(setup.val.tip)} val samples of `{Path(setup.val_rec.source).name}`.\n\n"
            "Offset-removed tip RMSE (the mean tip offset of each model is removed, as in results.json):\n\n"
            f"| model | RMSE [mm] |\n|---|---|\n{rows}\n")


def log_rerun(setup: Setup, preds: dict[str, torch.Tensor], path: Path,
              std: dict[str, torch.Tensor] | None = None) -> None:
    """Rerun .rrd of the val recording, with its own blueprint (:func:`hardware_blueprint`).

    Static: the measured and predicted val paths [m] and, for models in ``std`` (σ per sample
    [m], shape (N,) or (N, 3)), a ±2σ band of ellipsoids. On the timeline ``sample``: the
    measured and predicted tips, the CC model's backbone, each model's offset-removed error
    [mm] (all in one plot, colours as in 3D, RMSE in the legend) and its predicted 2σ [mm].
    """
    import rerun as rr

    sigma = _check_std(std, preds)
    errors = {name: centered_errors_mm(p, setup.val.tip) for name, p in preds.items()}
    rec = rr.RecordingStream("dacr_learn_hardware", recording_id=f"{setup.spec.name}-{Path(path).stem}")
    rec.set_sinks(rr.FileSink(str(path)))
    rec.send_blueprint(hardware_blueprint(errors, bool(sigma)), make_active=True, make_default=True)
    rec.send_recording_name(f"{setup.spec.name}: val tip paths ({Path(setup.val_rec.source).name})")
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_paths(rec, setup, preds, sigma)
    rmse = _log_samples(rec, setup, preds, errors, sigma)
    rec.log("summary", rr.TextDocument(_summary(setup, rmse), media_type="text/markdown"), static=True)
    rec.flush()
    rec.disconnect()
