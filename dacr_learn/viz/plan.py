"""Rerun recording of a follow-the-leader insertion (no maths): the path, its traversed part, the robot's body and
the arm at every step, and the tip error and shape deviation as curves, from arrays the caller computed (e.g.
``python -m dacr_learn.plan ftl --rerun FILE.rrd``). Metres; the timeline ``step``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .arm import log_arm
from .layout import full_range_plot, time_panel_at_end
from .scene import log_frames, log_path

TIMELINE = "step"
PATH_COLOR = (150, 150, 160)
TRAVERSED_COLOR = (40, 110, 230)
BODY_COLOR = (240, 190, 30)


def plan_blueprint() -> rrb.Blueprint:
    scene = rrb.Spatial3DView(origin="plan", name="path (grey), traversed (blue), robot (yellow), arm (capsules)")
    plots = [full_range_plot(TIMELINE, origin=f"metrics/{q}", from_zero=True, name=label)
             for q, label in (("shape_deviation", "shape deviation, mean and max [% of L]"),
                              ("tip_error", "tip error [L], log10"))]
    return rrb.Blueprint(rrb.Horizontal(scene, rrb.Vertical(*plots), column_shares=[3, 2]),
                         time_panel_at_end(TIMELINE), collapse_panels=True)


def record_insertion(file: Path, path: Any, traversed: list[np.ndarray], bodies: Any, tips: Any,
                     length: float, shape_dev: Any, shape_dev_max: Any, tip_err: Any,
                     arm_frames: Any | None = None, bases: Any | None = None) -> None:
    """Write ``file``: the path (W, 3) (static), per step k the traversed polyline ``traversed[k]`` (n_k, 3),
    the body (P, 3) of ``bodies`` (T, P, 3), the tip frame of ``tips`` (T, 4, 4), with ``arm_frames`` (T, F, 4, 4)
    the arm (capsules between its frames) and the mount to ``bases`` (T, 4, 4); curves of shape_dev,
    shape_dev_max (T,) [m] (as % of ``length`` L [m]) and log10 of tip_err (T,) / L."""
    bodies, tips = np.asarray(bodies, dtype=np.float64), np.asarray(tips, dtype=np.float64)
    file.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("dacr_learn_plan")
    rec.set_sinks(rr.FileSink(str(file)), default_blueprint=plan_blueprint())
    rec.log("plan", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    scale = 0.01 * length
    rec.log("plan/path", rr.LineStrips3D([np.asarray(path)], colors=PATH_COLOR, radii=0.3 * scale), static=True)
    for k in range(bodies.shape[0]):
        rec.set_time(TIMELINE, sequence=k)
        log_path(rec, "plan/traversed", traversed[k], color=TRAVERSED_COLOR, radius=0.7 * scale)
        log_path(rec, "plan/body", bodies[k], color=BODY_COLOR, radius=0.4 * scale)
        log_frames(rec, "plan/tip", tips[k:k + 1], axis_length=5 * scale)
        if arm_frames is not None:
            log_arm(rec, "plan/arm", np.asarray(arm_frames[k]), radius=2 * scale, axis_length=4 * scale,
                    mount=None if bases is None else np.asarray(bases[k]), mount_radius=1.5 * scale)
    steps = [rr.TimeColumn(TIMELINE, sequence=np.arange(bodies.shape[0]))]
    for entity, name, values in (("metrics/shape_deviation/mean", "mean", 100 * np.asarray(shape_dev) / length),
                                 ("metrics/shape_deviation/max", "max", 100 * np.asarray(shape_dev_max) / length),
                                 ("metrics/tip_error/log10", "tip error",
                                  np.log10(np.maximum(np.asarray(tip_err) / length, 1e-18)))):
        rec.log(entity, rr.SeriesLines(names=[name]), static=True)
        rec.send_columns(entity, indexes=steps, columns=rr.Scalars.columns(scalars=values))
    rec.disconnect()
