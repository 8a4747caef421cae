"""Rerun 3D scene helpers for continuum robots (no Lightning): backbones, tip frames, workspace.

All functions log to an explicit :class:`rerun.RecordingStream` (never the global one); the scene
is in metres. Used by :mod:`dacr_learn.viz.logger` (the Lightning callback), the controller example
and the hardware evaluation.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import rerun as rr
import torch
from matplotlib import colormaps

__all__ = ["DEFAULT_ERROR_RANGE", "VISUAL_KEYS", "colour_note", "error_colours", "log_colour_scale", "log_frames",
           "log_path", "log_scene", "log_workspace"]

VISUAL_KEYS = ("backbone", "backbone_true", "backbone_pred", "pose_true", "pose_pred", "workspace_points",
               "workspace_error")

AXIS_COLORS = np.array([[230, 40, 40], [40, 180, 40], [40, 90, 230]], dtype=np.uint8)
AXIS_COLORS_LIGHT = np.array([[255, 165, 165], [165, 235, 165], [165, 190, 255]], dtype=np.uint8)
BACKBONE_COLOR = (90, 90, 90)
BACKBONE_TRUE_COLOR = (30, 110, 220)     # the data's own backbone where it is not the CC one (Cosserat)
BACKBONE_PRED_COLOR = (235, 150, 40)     # the learned segment ends, joined
TIP_ERROR_COLOR = (255, 120, 0)
DEFAULT_ERROR_RANGE = (1e-6, 1e-2)  # [m]: workspace colours run over log10(error) from 1 µm to 10 mm

def _to_numpy(x: Any) -> np.ndarray:
    """Tensor / array-like -> float32 numpy array on the CPU (no gradient)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float32).numpy()
    return np.asarray(x, dtype=np.float32)


def _checked(name: str, x: Any, tail: tuple[int, ...], ndim: int) -> np.ndarray:
    """Convert ``x`` and check it has ``ndim`` dims ending in ``tail``; ValueError otherwise."""
    arr = _to_numpy(x)
    if arr.ndim != ndim or arr.shape[arr.ndim - len(tail):] != tail:
        want = ", ".join(["…"] * (ndim - len(tail)) + [str(t) for t in tail])
        raise ValueError(f"{name} must have shape ({want}), got {tuple(arr.shape)}")
    return arr


def log_path(
    recording: rr.RecordingStream, entity: str, points: Any, color: Any = BACKBONE_COLOR,
    radius: float = 0.001,
) -> None:
    """Log one curve (N, 3) or curves (k, N, 3) [m] as rr.LineStrips3D, one RGB(A) ``color``, ``radius`` [m]."""
    pts = _to_numpy(points)
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3) or (k, N, 3), got {tuple(pts.shape)}")
    strips = pts.reshape(-1, pts.shape[-2], 3)
    recording.log(entity, rr.LineStrips3D(strips, colors=color, radii=radius))


def log_frames(
    recording: rr.RecordingStream, entity: str, poses: Any, *, axis_length: float = 0.01,
    colors: np.ndarray = AXIS_COLORS, radius: float | None = None,
) -> None:
    """Log frames (k, 4, 4) [m] as x/y/z arrows of ``axis_length`` [m], ``radius`` thick (default
    ``axis_length / 15``), coloured by ``colors`` (3, 3) uint8."""
    T = _checked(f"poses of {entity!r}", poses, (4, 4), 3)
    axes = T[:, :3, :3].transpose(0, 2, 1).reshape(-1, 3)  # rows: x, y, z axis of each frame
    origins = np.repeat(T[:, :3, 3], 3, axis=0)
    colors = np.tile(colors, (T.shape[0], 1))
    radii = axis_length / 15 if radius is None else radius
    arrows = rr.Arrows3D(vectors=axes * axis_length, origins=origins, colors=colors, radii=radii)
    recording.log(entity, arrows)


def _length_label(metres: float) -> str:
    """1e-6 -> "1 µm", 1e-4 -> "0.1 mm", 0.01 -> "10 mm"."""
    return f"{metres * 1e6:g} µm" if metres < 1e-5 else f"{metres * 1e3:g} mm"


def colour_note(error_range: tuple[float, float] = DEFAULT_ERROR_RANGE, cmap: str = "viridis") -> str:
    """One line naming the fixed colour scale, e.g. ``"log colours 1 µm → 10 mm"`` (viridis: dark → bright)."""
    lo, hi = error_range
    return f"log colours {_length_label(lo)} → {_length_label(hi)}" + ("" if cmap == "viridis" else f", {cmap}")


def error_colours(error: np.ndarray, error_range: tuple[float, float], cmap: str = "viridis") -> np.ndarray:
    """RGB uint8 colours (N, 3) of errors [m] on a fixed log scale (clipped to ``error_range``): the same at every
    step and in every run."""
    lo, hi = error_range
    if not 0 < lo < hi:
        raise ValueError(f"error_range must be (low, high) with 0 < low < high [m], got {error_range}")
    t = (np.log10(np.clip(error, lo, hi)) - np.log10(lo)) / (np.log10(hi) - np.log10(lo))
    return (colormaps[cmap](t)[:, :3] * 255).astype(np.uint8)


def log_colour_scale(
    recording: rr.RecordingStream, entity: str, points: np.ndarray, *,
    error_range: tuple[float, float] = DEFAULT_ERROR_RANGE, cmap: str = "viridis",
) -> None:
    """A colour bar in 3D (static): one labelled point per decade of ``error_range``, in a column
    beside the bounding box of ``points`` ``(N, 3)`` [m] (Rerun has no colour-bar widget)."""
    lo, hi = error_range
    decades = np.logspace(np.log10(lo), np.log10(hi), int(round(np.log10(hi / lo))) + 1)
    low, high = points.min(0), points.max(0)
    size = float(np.max(high - low)) or 0.01
    column = np.zeros((len(decades), 3), dtype=np.float32)
    column[:, 0] = high[0] + 0.25 * size
    column[:, 1] = 0.5 * (low[1] + high[1])
    column[:, 2] = np.linspace(low[2], low[2] + size, len(decades))
    recording.log(entity, rr.Points3D(column, colors=error_colours(decades, error_range, cmap), radii=0.03 * size,
                                      labels=[_length_label(d) for d in decades], show_labels=True), static=True)


def log_workspace(
    recording: rr.RecordingStream, entity: str, points: Any, error: Any, *,
    cmap: str = "viridis", radius: float = 0.0006, error_range: tuple[float, float] = DEFAULT_ERROR_RANGE,
    max_points: int | None = None,
) -> float:
    """Log workspace points (N, 3) [m] coloured by ``error`` (N,) [m] on the fixed log scale ``error_range``
    (:func:`error_colours`), at most ``max_points`` evenly strided (the statistics use all), with a rr.TextLog of
    the max and mean error [mm]; returns the max error [m].
    """
    pts = _checked("workspace_points", points, (3,), 2)
    err = _checked("workspace_error", error, (pts.shape[0],), 1)
    stride = 1 if max_points is None or len(pts) <= max_points else -(-len(pts) // max_points)
    shown = slice(None, None, stride)
    colours = error_colours(err[shown], error_range, cmap)
    recording.log(entity, rr.Points3D(pts[shown], colors=colours, radii=radius))
    max_err = float(err.max()) if err.size else 0.0
    mean_mm = 1e3 * float(err.mean()) if err.size else 0.0
    text = f"workspace: max tip error {1e3 * max_err:.3f} mm, mean {mean_mm:.3f} mm over "
    text += f"{err.size} samples ({colour_note(error_range, cmap)})"
    recording.log(entity, rr.TextLog(text, level="INFO"))
    return max_err


def log_scene(
    recording: rr.RecordingStream, prefix: str, visual: Mapping[str, Any], *,
    axis_length: float = 0.01, cmap: str = "viridis", error_range: tuple[float, float] = DEFAULT_ERROR_RANGE,
    max_points: int | None = None,
) -> None:
    """Log a visual batch under ``prefix`` at the recording's current time (set it first). ``visual`` may hold any
    of (tensors or arrays, metres): ``backbone`` (k, P, 3) (grey: CC), ``backbone_true`` (k, P', 3) (blue: the data's
    own, e.g. Cosserat), ``backbone_pred`` (k, P'', 3) (orange: learned segment ends or body), ``pose_true``,
    ``pose_pred`` (k, 4, 4), ``workspace_points`` (N, 3) with optional ``workspace_error`` (N,) (:func:`log_workspace`;
    a static colour bar at ``<prefix>/workspace/colour_scale`` the first time). Unknown keys are a ValueError.
    """
    unknown = sorted(set(visual) - set(VISUAL_KEYS))
    if unknown:
        raise ValueError(f"unknown visual keys {unknown}; expected a subset of {list(VISUAL_KEYS)}")
    shapes = {"backbone": ((3,), 3), "backbone_true": ((3,), 3), "backbone_pred": ((3,), 3), "pose_true": ((4, 4), 3),
              "pose_pred": ((4, 4), 3)}
    arrays = {k: _checked(f"visual[{k!r}]", visual[k], *shapes[k]) for k in shapes if k in visual}
    for key, color in (("backbone", BACKBONE_COLOR), ("backbone_true", BACKBONE_TRUE_COLOR),
                       ("backbone_pred", BACKBONE_PRED_COLOR)):
        if key in arrays:
            log_path(recording, f"{prefix}/{key}", arrays[key], color=color)
    for key, colors in (("pose_true", AXIS_COLORS), ("pose_pred", AXIS_COLORS_LIGHT)):
        if key in arrays:
            entity = f"{prefix}/tip_{key.removeprefix('pose_')}"
            log_frames(recording, entity, arrays[key], axis_length=axis_length, colors=colors)
    if "pose_true" in arrays and "pose_pred" in arrays:
        tips = np.stack([arrays[k][:, :3, 3] for k in ("pose_true", "pose_pred")], 1)
        log_path(recording, f"{prefix}/tip_error", tips, color=TIP_ERROR_COLOR, radius=0.0004)
    if "workspace_points" in visual:
        points = _checked("visual['workspace_points']", visual["workspace_points"], (3,), 2)
        error = visual.get("workspace_error", np.zeros(len(points)))
        log_workspace(recording, f"{prefix}/workspace", points, error, cmap=cmap, error_range=error_range,
                      max_points=max_points)
        log_colour_scale(recording, f"{prefix}/workspace/colour_scale", points, error_range=error_range, cmap=cmap)
    elif "workspace_error" in visual:
        raise ValueError("visual['workspace_error'] needs visual['workspace_points']")
