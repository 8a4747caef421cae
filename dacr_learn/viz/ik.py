"""Rerun view of an IK solve: per target, its frame and the K solutions as ghost backbones (no Lightning).

:func:`log_ik_solutions` logs to an explicit :class:`rerun.RecordingStream`; the scene is in metres. The targets
are laid out side by side along x (``spacing``) so that the solutions of each can be told apart; a successful
solution is drawn in its own translucent colour, a failed one in red.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from matplotlib import colormaps

from .scene import log_frames

__all__ = ["ik_blueprint", "log_ik_solutions"]

FAILED_COLOR = (220, 40, 40, 200)


def log_ik_solutions(recording: rr.RecordingStream, prefix: str, targets: Any, backbones: Any, success: Any, *,
                     spacing: float | None = None, axis_length: float = 0.02, alpha: int = 110) -> None:
    """Log targets (B, 4, 4) [m] at ``<prefix>/target_<b>/frame`` and their solutions' backbones (B, K, P, 3) [m] at
    ``<prefix>/target_<b>/solution_<k>`` (translucent; red where success (B, K) is False), the targets ``spacing`` [m]
    apart along x (default 1.2 × the largest backbone extent)."""
    poses, lines = (np.asarray(a.detach().cpu() if hasattr(a, "detach") else a, dtype=np.float32)
                    for a in (targets, backbones))
    ok = np.asarray(success, dtype=bool)
    if (poses.ndim != 3 or poses.shape[1:] != (4, 4) or lines.ndim != 4 or lines.shape[-1] != 3
            or lines.shape[0] != poses.shape[0] or ok.shape != lines.shape[:2]):
        raise ValueError(f"backbones (B, K, P, 3) and success (B, K) must match targets (B, 4, 4), got "
                         f"{lines.shape}, {ok.shape}, {poses.shape}")
    if spacing is None:
        spacing = 1.2 * float(np.abs(lines[..., :2]).max() * 2 + axis_length)
    k = lines.shape[1]
    palette = (np.asarray(colormaps["tab10"](np.arange(k) % 10))[:, :3] * 255).astype(np.uint8)
    for b in range(poses.shape[0]):
        shift = np.array([b * spacing, 0.0, 0.0], dtype=np.float32)
        frame = poses[b:b + 1].copy()
        frame[:, :3, 3] += shift
        log_frames(recording, f"{prefix}/target_{b}/frame", frame, axis_length=axis_length)
        for j in range(k):
            color = (*palette[j], alpha) if ok[b, j] else FAILED_COLOR
            recording.log(f"{prefix}/target_{b}/solution_{j}",
                          rr.LineStrips3D([lines[b, j] + shift], colors=[color], radii=0.0012))


def ik_blueprint(prefix: str = "ik") -> rrb.Blueprint:
    """One 3D view of the solve, the camera looking at all targets."""
    return rrb.Blueprint(rrb.Spatial3DView(origin=prefix, name="IK solutions"), collapse_panels=True)
