"""Figures and Rerun recordings of predicted vs measured tip paths on a validation recording."""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import torch

from ..metrics import offset_removed_errors
from .benchmark import Setup
from .registry import MODELS

COLORS = {"measured": (20, 20, 20), "cc": (31, 119, 180)}
PALETTE = [(214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (255, 0, 255), (0, 150, 136),
           (0, 0, 128), (255, 215, 0), (128, 0, 0)]
# one colour per registered model besides cc: k = 1 … 14 in registry order never wraps onto another's


def _color(name: str, k: int) -> tuple[int, int, int]:
    """A model's colour: fixed by its registry position (so the PNG, which shows a few models, and the
    Rerun recording, which shows all, agree); ``k`` (its position in the plot) only for other names."""
    if name in MODELS:
        k = MODELS.index(name) + 1
    return COLORS.get(name, PALETTE[k % len(PALETTE)])


def label_runs(labels: tuple[str, ...]) -> list[slice]:
    """Consecutive rows with the same label (ignoring a trailing '_hold'), as slices."""
    groups = itertools.groupby(lab.removesuffix("_hold") for lab in labels)
    ends = list(itertools.accumulate(sum(1 for _ in rows) for _, rows in groups))
    return [slice(start, end) for start, end in zip([0, *ends], ends, strict=False)]


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
    errors = {name: centered_errors_mm(pred, setup.val.tip) for name, pred in preds.items()}
    for k, (name, rmse) in enumerate(rmse_mm(errors).items(), start=1):
        axes[2].plot(errors[name], color=np.array(_color(name, k)) / 255, lw=1, label=f"{name} (RMSE {rmse:.2f} mm)")
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


LEGEND_ROOM = 0.25  # top fraction of the error plot kept free of curves, for its legend (three lines)


def error_axis_max(errors: dict[str, np.ndarray]) -> float:
    """Top of the error plot [mm] for the plotted models' ``errors``: their largest error over
    (1 − LEGEND_ROOM), so every point is visible and the legend (top right) lies above the curves."""
    top = max((float(e.max()) for e in errors.values() if e.size), default=0.0) / (1 - LEGEND_ROOM)
    return top if top > 0 else 1.0  # a perfect model must not collapse the axis


def rmse_mm(errors: dict[str, np.ndarray]) -> dict[str, float]:
    """Model -> RMSE [mm] of its offset-removed errors [mm]."""
    return {name: float(np.sqrt((e**2).mean())) for name, e in errors.items()}


def shown_models(errors: dict[str, np.ndarray], default: str | None = None, shown: int = 3) -> list[str]:
    """The models the recording shows by default (error plot and 3D view): the default model (if it
    is one of ``errors``) and the lowest-val-RMSE others, ``shown`` models in all, default first."""
    rmse = rmse_mm(errors)
    first = [default] if default in errors else []
    return first + sorted((n for n in errors if n not in first), key=rmse.__getitem__)[:max(shown - len(first), 0)]


def _hidden(entities: list[str]) -> dict[str, list]:
    """View overrides hiding ``entities`` (still in the recording and the blueprint panel: one click shows one)."""
    import rerun.blueprint as rrb

    return {e: [rrb.EntityBehavior(visible=False)] for e in entities}


def hardware_blueprint(errors: dict[str, np.ndarray], with_std: bool, shown: int = 3, default: str | None = None):
    """Layout for :func:`log_rerun` (``errors``: model -> offset-removed errors [mm]): left the 3D view and the
    :func:`shown_models`' error per val sample (and predicted 2σ with ``with_std``), right every model's val RMSE bar
    and table; the other models hidden (one click away). Opens at the last sample.
    """
    import rerun.blueprint as rrb

    from ...viz.layout import full_range_plot, time_panel_at_end

    visible = shown_models(errors, default, shown)
    hidden = [n for n in errors if n not in visible]
    hidden_3d = [n for n in hidden if n != "cc"]            # the CC model's path stays, as the reference
    top = error_axis_max({n: errors[n] for n in visible})
    what = (f"default {visible[0]} and the best {len(visible) - 1} others" if visible and visible[0] == default
            else f"the best {len(visible)}")
    plots = [full_range_plot(SAMPLE_TIMELINE, origin="errors", axis_y=rrb.ScalarAxis(range=(0.0, top)),
                             overrides=_hidden([f"errors/{n}" for n in hidden]),
                             name=f"offset-removed tip error [mm] per val sample: {what} "
                                  f"({len(hidden)} more hidden)")]
    if with_std:
        plots.append(full_range_plot(SAMPLE_TIMELINE, origin="sigma", overrides=_hidden([f"sigma/{n}" for n in hidden]),
                                     name="predicted 2σ [mm] (uncertainty)"))
    bars = rrb.BarChartView(origin="rmse", name=f"val RMSE [mm] of all {len(errors)} models, best first",
                            plot_legend=rrb.PlotLegend(rrb.Corner2D.LeftTop, visible=True))
    table = rrb.TextDocumentView(origin="summary", name="val RMSE table")
    overrides = _hidden([f"world/{kind}/{n}" for n in hidden_3d for kind in ("paths", "tip", "band_2sigma")])
    names = ", ".join(dict.fromkeys([*visible, "cc"] if "cc" in errors else visible))
    scene = rrb.Spatial3DView(origin="world", overrides=overrides,
                              name=f"val tip paths: measured (white) and {names}; CC backbone (blue)")
    left = rrb.Vertical(scene, *plots, row_shares=[3] + [2] * len(plots))
    right = rrb.Vertical(bars, table, row_shares=[1, 1])
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[5, 3]), time_panel_at_end(SAMPLE_TIMELINE),
                         collapse_panels=True)


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
                 sigma: dict[str, np.ndarray], default: str | None = None) -> dict[str, float]:
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
    rmse = rmse_mm(errors)
    for k, (name, pred) in enumerate(preds.items(), start=1):
        color, err = _color(name, k), errors[name]
        rec.log(f"world/tip/{name}", rr.Points3D.from_fields(colors=[color], radii=0.0015), static=True)
        rec.send_columns(f"world/tip/{name}", index, rr.Points3D.columns(positions=pred.numpy()))
        legend = f"{name} ({rmse[name]:.2f} mm{', default' if name == default else ''})"
        rec.log(f"errors/{name}", rr.SeriesLines(names=[legend], colors=[color]), static=True)
        rec.send_columns(f"errors/{name}", index, rr.Scalars.columns(scalars=err))
        if name in sigma:
            two_sigma_mm = 2e3 * np.linalg.norm(sigma[name], axis=1)
            rec.log(f"sigma/{name}", rr.SeriesLines(names=[f"{name} 2σ"], colors=[color]), static=True)
            rec.send_columns(f"sigma/{name}", index, rr.Scalars.columns(scalars=two_sigma_mm))
    return rmse


def _log_rmse_bars(rec, rmse: dict[str, float], colors: dict[str, tuple[int, int, int]]) -> None:
    """Static: one rr.BarChart per model at :func:`rmse_entity`, its bar at x = rank (1: the lowest RMSE) in
    the model's colour; the viewer's legend lists the entities, so it reads rank and name, best first."""
    import rerun as rr

    for rank, name in enumerate(sorted(rmse, key=rmse.__getitem__), start=1):
        rec.log(rmse_entity(rank, name), rr.BarChart([rmse[name]], abscissa=[rank], color=colors[name]), static=True)


def rmse_entity(rank: int, name: str) -> str:
    """Entity of a model's RMSE bar: ``rmse/<rank>_<model>`` (rank 1 = lowest RMSE)."""
    return f"rmse/{rank}_{name}"


def _summary(setup: Setup, rmse: dict[str, float], default: str | None = None) -> str:
    ranked = sorted(rmse, key=rmse.__getitem__)
    rows = "\n".join(f"| {rank} | {name}{' (default)' if name == default else ''} | {rmse[name]:.2f} |"
                     for rank, name in enumerate(ranked, start=1))
    return (f"**{setup.spec.name}**, {len(setup.val.tip)} val samples of `{Path(setup.val_rec.source).name}`.\n\n"
            "Offset-removed tip RMSE (the mean tip offset of each model is removed, as in results.json):\n\n"
            f"| # | model | RMSE [mm] |\n|---|---|---|\n{rows}\n")


def log_rerun(setup: Setup, preds: dict[str, torch.Tensor], path: Path,
              std: dict[str, torch.Tensor] | None = None, default: str | None = None) -> None:
    """Rerun .rrd of the val recording with :func:`hardware_blueprint` (showing ``default``): static paths [m],
    ±2σ ellipsoids for models in ``std`` (σ [m], (N,) or (N, 3)) and RMSE bars; on the ``sample`` timeline the tips,
    the CC backbone, each model's offset-removed error [mm] and predicted 2σ [mm].
    """
    import rerun as rr

    sigma = _check_std(std, preds)
    errors = {name: centered_errors_mm(p, setup.val.tip) for name, p in preds.items()}
    rec = rr.RecordingStream("dacr_learn_hardware", recording_id=f"{setup.spec.name}-{Path(path).stem}")
    rec.set_sinks(rr.FileSink(str(path)))
    rec.send_blueprint(hardware_blueprint(errors, bool(sigma), default=default), make_active=True, make_default=True)
    rec.send_recording_name(f"{setup.spec.name}: val tip paths ({Path(setup.val_rec.source).name})")
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_paths(rec, setup, preds, sigma)
    rmse = _log_samples(rec, setup, preds, errors, sigma, default)
    _log_rmse_bars(rec, rmse, {name: _color(name, k) for k, name in enumerate(preds, start=1)})
    rec.log("summary", rr.TextDocument(_summary(setup, rmse, default), media_type="text/markdown"), static=True)
    rec.flush()
    rec.disconnect()
