"""What a training recording shows: metric naming, plot grouping and the blueprint (no Lightning).

Rerun 0.41 plots have no logarithmic axis, so every plotted metric is logged twice: its value at ``metrics/<name>``
and ``log10(value)`` at ``metrics_log10/<name>``. One plot per quantity and unit (:func:`metric_groups`), test
metrics in a table; the layout: :func:`default_blueprint` (what it looks like: docs/rerun.md, "Training run").
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping

import rerun as rr
import rerun.blueprint as rrb
from rerun.blueprint.components import PlayState

__all__ = [
    "HPARAMS_ENTITY", "CONFIG_ENTITY", "LOG10_ROOT", "METRICS_ROOT", "SCENE_ROOT", "STEP_TIMELINE",
    "SUMMARY_ENTITY", "WORKSPACE_ENTITY", "default_blueprint", "full_range_plot", "log10_entity", "metric_entity",
    "metric_groups", "series_style", "summary_markdown", "time_panel_at_end",
]

STEP_TIMELINE = "step"
METRICS_ROOT = "metrics"
LOG10_ROOT = "metrics_log10"
HPARAMS_ENTITY = "hparams"
CONFIG_ENTITY = "config"
SUMMARY_ENTITY = "summary"
SCENE_ROOT = "scene"
WORKSPACE_ENTITY = f"{SCENE_ROOT}/workspace"

SPLITS = ("train", "val", "test")
NOT_PLOTTED = ("epoch",)
QUANTITY_TITLES = {"pos_err": "tip position error", "rot_err": "tip rotation error", "joint_err": "joint error",
                   "constraint_residual": "constraint residual", "loss": "loss", "nll": "negative log-likelihood",
                   "out_of_limits": "outside the joint limits"}
SIGNED = ("nll",)    # quantities that may be negative: plotted with linear values in the log10 tab too
UNIT_TITLES = {"mm": "mm", "deg": "°", "m": "m", "pct": "% of robot length", "": ""}
SHARE_PCT = ("out_of_limits",)      # their "pct" is a share of the samples [%], not a length
UNIT_PREFERENCE = ("mm", "deg", "m", "", "pct")  # a quantity logged in several units is plotted in the first
STAT_COLORS = {"": (255, 127, 14), "mean": (255, 127, 14), "p95": (214, 39, 40), "max": (148, 103, 189)}
TRAIN_COLORS = {"": (31, 119, 180), "mean": (23, 190, 207), "p95": (44, 160, 44), "max": (140, 86, 75)}
_KEY = re.compile(r"^(?P<quantity>.+?)(?:_(?P<stat>mean|p95|max))?(?:_(?P<unit>mm|deg|pct|m))?$")


def metric_entity(name: str, root: str = METRICS_ROOT) -> str:
    """Entity path of a metric: ``"val/pos_err"`` -> ``"metrics/val/pos_err"`` (parts escaped)."""
    parts = [rr.escape_entity_path_part(p) for p in str(name).split("/") if p]
    return "/".join([root, *parts])


def log10_entity(name: str) -> str:
    """Entity path of the log10 copy of a metric: ``"metrics_log10/<name>"``."""
    return metric_entity(name, LOG10_ROOT)


def _split_key(name: str) -> tuple[str, str]:
    """``"val/pos_err_mean_mm"`` -> ("val", "pos_err_mean_mm"); ``"train_loss"`` -> ("train", "loss")."""
    split, _, key = name.rpartition("/")
    if not split:
        split = next((s for s in SPLITS if name.startswith(f"{s}_")), "")
        key = name[len(split) + 1:] if split else name
    return split, key


def _parse(key: str) -> tuple[str, str, str]:
    """``"pos_err_p95_mm"`` -> ("pos_err", "p95", "mm"); ``"loss"`` -> ("loss", "", "")."""
    m = _KEY.match(key)
    return (m["quantity"], m["stat"] or "", m["unit"] or "") if m else (key, "", "")


def is_plotted(name: str) -> bool:
    """Train/val metrics are curves; test metrics (one point) and ``epoch`` go to the summary table only."""
    return _split_key(name)[0] != "test" and name not in NOT_PLOTTED


def series_style(name: str) -> tuple[str, tuple[int, int, int]]:
    """Legend label and colour of a metric's series: ``"val/pos_err_p95_mm"`` -> ("val p95", red)."""
    split, key = _split_key(name)
    quantity, stat, _ = _parse(key)
    colors = TRAIN_COLORS if split == "train" else STAT_COLORS
    label = " ".join(p for p in (split, stat or ("" if quantity in QUANTITY_TITLES else key)) if p)
    return label or name, colors.get(stat, colors[""])


def metric_groups(names: Iterable[str]) -> dict[str, list[str]]:
    """Plot title -> plotted metric names (train and val of one quantity in one unit, sorted); a quantity logged in
    several units is plotted in the first of ``UNIT_PREFERENCE`` (the others stay in the summary table)."""
    by_quantity: dict[str, dict[str, list[str]]] = {}
    for name in sorted(n for n in set(names) if is_plotted(n)):
        quantity, _, unit = _parse(_split_key(name)[1])
        by_quantity.setdefault(quantity, {}).setdefault(unit, []).append(name)
    groups: dict[str, list[str]] = {}
    for quantity in sorted(by_quantity, key=lambda q: (q != "loss", q)):
        units = by_quantity[quantity]
        unit = min(units, key=lambda u: UNIT_PREFERENCE.index(u) if u in UNIT_PREFERENCE else len(UNIT_PREFERENCE))
        title = QUANTITY_TITLES.get(quantity, quantity)
        unit_title = "% of samples" if quantity in SHARE_PCT and unit == "pct" else UNIT_TITLES.get(unit, unit)
        groups[f"{title} [{unit_title}]" if unit else title] = units[unit]
    return groups


def summary_markdown(latest: Mapping[str, tuple[int, float]]) -> str:
    """Markdown table of the latest value of every metric: one row per key, columns train/val/test."""
    cells = {_split_key(name): value for name, (_, value) in latest.items()}
    splits = sorted({s for s, _ in cells}, key=lambda s: (s not in SPLITS, SPLITS.index(s) if s in SPLITS else 0, s))
    lines = ["| metric | " + " | ".join(s or "—" for s in splits) + " |", "|---" * (len(splits) + 1) + "|"]
    for key in sorted({k for _, k in cells}):
        row = [_fmt(cells[s, key]) if (s, key) in cells else "" for s in splits]
        lines.append(f"| {key} | " + " | ".join(row) + " |")
    step = max((s for s, _ in latest.values()), default=0)
    return f"Latest value of every metric (at or before step {step}).\n\n" + "\n".join(lines)


def _fmt(value: float) -> str:
    return f"{value:.4g}" if math.isfinite(value) else str(value)


def full_range_plot(
    timeline: str, *, name: str, origin: str = "/", contents: Iterable[str] | str = "$origin/**",
    from_zero: bool = False, legend: rrb.Corner2D | None = rrb.Corner2D.RightTop, **kwargs,
) -> rrb.TimeSeriesView:
    """A named time-series plot of ``origin``/``contents`` that shows every point of ``timeline`` (Rerun's default is
    a ±1000-step window around the cursor): the visible range and x axis cover the whole timeline (from 0 with
    ``from_zero``). ``legend``: its corner, or None. Other keyword arguments (``axis_y``, ``overrides``, …) go to
    rrb.TimeSeriesView.
    """
    whole = rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.infinite())
    start = rrb.TimeRangeBoundary.absolute(seq=0) if from_zero else rrb.TimeRangeBoundary.infinite()
    axis_x = rrb.TimeAxis(view_range=rrb.TimeRange(start=start, end=rrb.TimeRangeBoundary.infinite()))
    plot_legend = rrb.PlotLegend(visible=False) if legend is None else rrb.PlotLegend(legend, visible=True)
    return rrb.TimeSeriesView(origin=origin, contents=contents, time_ranges=[whole], axis_x=axis_x, name=name,
                              plot_legend=plot_legend, **kwargs)


def time_panel_at_end(timeline: str) -> rrb.TimePanel:
    """The time panel on ``timeline`` at its last time, in follow mode (a live recording stays current),
    collapsed: a recording opens on its final state instead of auto-playing from an empty start."""
    return rrb.TimePanel(timeline=timeline, play_state=PlayState.Following, state="collapsed")


def _plots(groups: Mapping[str, list[str]], log10: bool) -> list[rrb.TimeSeriesView]:
    plots = []
    for title, names in groups.items():
        log = log10 and _parse(_split_key(names[0])[1])[0] not in SIGNED
        entity = log10_entity if log else metric_entity
        plots.append(full_range_plot(STEP_TIMELINE, contents=[entity(n) for n in names], from_zero=True,
                                     name=f"{title}, log10" if log else title))
    return plots


def default_blueprint(metric_names: Iterable[str] = (), colour_note: str = "") -> rrb.Blueprint:
    """Layout of a training recording (docs/rerun.md): full-range metric plots (log10 and linear tabs) on the
    left; the 3D validation samples, the workspace error cloud and tabs (metrics table, hparams, config, log) on
    the right; the time panel on ``step`` at the last step (follow mode).
    """
    groups = metric_groups(metric_names)
    log_plots = _plots(groups, log10=True) or [rrb.TimeSeriesView(origin=LOG10_ROOT, name="metrics, log10")]
    lin_plots = _plots(groups, log10=False) or [rrb.TimeSeriesView(origin=METRICS_ROOT, name="metrics")]
    curves = rrb.Tabs(rrb.Vertical(*log_plots, name="curves (log10)"), rrb.Vertical(*lin_plots, name="curves (linear)"))
    robot = rrb.Spatial3DView(origin=SCENE_ROOT, contents=["+ $origin/**", f"- {WORKSPACE_ENTITY}/**"],
                              name="val samples: backbones, tip frames (true dark, predicted light), errors")
    workspace = rrb.Spatial3DView(origin=SCENE_ROOT, contents=[f"+ {WORKSPACE_ENTITY}/**"],
                                  name=f"workspace tip error{' (' + colour_note + ')' if colour_note else ''}")
    info = rrb.Tabs(rrb.TextDocumentView(origin=SUMMARY_ENTITY, name="metrics table"),
                    rrb.TextDocumentView(origin=HPARAMS_ENTITY, name="hparams"),
                    rrb.TextDocumentView(origin=CONFIG_ENTITY, name="config"),
                    rrb.TextLogView(origin="/", name="log"))
    right = rrb.Vertical(robot, rrb.Horizontal(workspace, info), row_shares=[3, 2])
    return rrb.Blueprint(rrb.Horizontal(curves, right, column_shares=[1, 1]), time_panel_at_end(STEP_TIMELINE),
                         collapse_panels=True)
