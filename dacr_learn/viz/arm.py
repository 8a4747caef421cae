"""Rerun 3D helpers for a rigid arm carrying a continuum robot (no Lightning, no maths): the arm's link frames
and capsules between them, the mount, a port, from arrays the caller computed (e.g. with dacr_learn.arm).

Like :mod:`.scene`, every function logs to an explicit :class:`rerun.RecordingStream`, in metres.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from .scene import log_frames

__all__ = ["ARM_COLOR", "MOUNT_COLOR", "PORT_COLOR", "WALL_COLOR", "capsules_between", "log_arm", "log_port", "z_to"]

ARM_COLOR = (200, 200, 210)
MOUNT_COLOR = (120, 120, 140)
PORT_COLOR = (230, 60, 60)
WALL_COLOR = (150, 170, 200, 60)
MIN_LINK = 1e-6       # [m]: consecutive frames closer than this (coincident joint frames) get no capsule


def _array(name: str, x: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    """x as a float64 array of ``shape`` (None: any size); ValueError naming ``name`` otherwise."""
    arr = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)):
        want = ", ".join("…" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape ({want}), got {tuple(arr.shape)}")
    return arr


def z_to(direction: np.ndarray) -> np.ndarray:
    """Quaternions (k, 4) xyzw of the shortest rotations turning +z onto unit directions (k, 3)
    ((z × d, 1 + z·d), normalised; d = −z: a half turn about x)."""
    quat = np.concatenate([np.stack([-direction[:, 1], direction[:, 0], np.zeros(len(direction))], -1),
                           1.0 + direction[:, 2:3]], axis=-1)
    quat[quat[:, 3] < 1e-12] = [1.0, 0.0, 0.0, 0.0]
    return quat / np.linalg.norm(quat, axis=-1, keepdims=True)


def capsules_between(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Capsules joining consecutive points (P, 3) [m]: (start points (k, 3), lengths (k,), quaternions (k, 4)
    xyzw turning +z onto each segment); segments shorter than :data:`MIN_LINK` are left out."""
    start, delta = points[:-1], np.diff(points, axis=0)
    length = np.linalg.norm(delta, axis=-1)
    keep = length > MIN_LINK
    start, delta, length = start[keep], delta[keep], length[keep]
    return start, length, z_to(delta / length[:, None])


def log_arm(recording: rr.RecordingStream, entity: str, frames: Any, *, radius: float = 0.04,
            axis_length: float = 0.06, color: Any = ARM_COLOR, mount: Any | None = None,
            mount_radius: float = 0.03) -> None:
    """The arm at one instant: its chain's frames (F, 4, 4) [m] (root to tip link) as x/y/z arrows at
    ``entity``/frames, capsules of ``radius`` [m] between consecutive frame origins at ``entity``/links, and with
    ``mount`` (4, 4) (the robot base in the same frame) a capsule from the tip link to it at ``entity``/mount."""
    poses = _array(f"frames of {entity!r}", frames, (None, 4, 4))
    log_frames(recording, f"{entity}/frames", poses, axis_length=axis_length)
    start, length, quat = capsules_between(poses[:, :3, 3])
    recording.log(f"{entity}/links", rr.Capsules3D(lengths=length, radii=radius, translations=start,
                                                  quaternions=quat, colors=color))
    if mount is not None:
        base = _array(f"mount of {entity!r}", mount, (4, 4))
        start, length, quat = capsules_between(np.stack([poses[-1, :3, 3], base[:3, 3]]))
        recording.log(f"{entity}/mount", rr.Capsules3D(lengths=length, radii=mount_radius, translations=start,
                                                      quaternions=quat, colors=MOUNT_COLOR))


def log_port(recording: rr.RecordingStream, entity: str, centre: Any, radius: float, *, axis: Any = (0.0, 0.0, 1.0),
             wall: float = 0.0, color: Any = PORT_COLOR) -> None:
    """A port (static): a ball of ``radius`` [m] around ``centre`` (3,) [m] at ``entity``/port and, with ``wall``
    > 0, a thin translucent plate of that radius [m] across the port ``axis`` (3,) at ``entity``/wall."""
    c = _array(f"centre of {entity!r}", centre, (3,))
    recording.log(f"{entity}/port", rr.Ellipsoids3D(centers=c[None], half_sizes=[[radius] * 3], colors=color,
                                                    fill_mode=rr.components.FillMode.Solid), static=True)
    if wall > 0:
        a = _array(f"axis of {entity!r}", axis, (3,))
        quat = z_to((a / np.linalg.norm(a))[None])
        recording.log(f"{entity}/wall", rr.Ellipsoids3D(centers=c[None], half_sizes=[[wall, wall, 0.1 * radius]],
                                                        quaternions=quat, colors=WALL_COLOR,
                                                        fill_mode=rr.components.FillMode.Solid), static=True)
