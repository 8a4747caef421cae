"""Rerun view of a scene's obstacles and of a body coloured by its clearance (no Lightning).

:func:`log_obstacles` logs spheres (ellipsoids), capsules, boxes and meshes of a :class:`~dacr_learn.scene.Scene`
[m]; :func:`log_body_clearance` logs a body's points as balls of the envelope radius, coloured by each ball's
clearance to the obstacles: red where it penetrates, orange where it is closer than the required clearance,
green from there to twice it and beyond.
"""
from __future__ import annotations

import numpy as np
import rerun as rr
import torch

from ..scene import Scene
from .arm import z_to

__all__ = ["clearance_colors", "log_body_clearance", "log_obstacles", "log_scene_solutions"]

OBSTACLE_COLOR = (150, 150, 160, 150)


def _rotation_quaternion(rot: np.ndarray) -> np.ndarray:
    from pytorch_kinematics.transforms import matrix_to_quaternion
    wxyz = matrix_to_quaternion(torch.from_numpy(rot)).numpy()
    return np.concatenate([wxyz[:, 1:], wxyz[:, :1]], 1)


def log_obstacles(recording: rr.RecordingStream, path: str, scene: Scene, color=OBSTACLE_COLOR) -> None:
    """Entities ``<path>/spheres``, ``/capsules``, ``/boxes``, ``/mesh_<i>`` (translucent grey)."""
    if scene.sphere_radius.numel():
        r = scene.sphere_radius.numpy()
        recording.log(f"{path}/spheres", rr.Ellipsoids3D(centers=scene.sphere_center.numpy(),
                                                          half_sizes=np.repeat(r[:, None], 3, 1), colors=color,
                                                          fill_mode="solid"))
    if scene.capsule_radius.numel():
        a, b = scene.capsule_a.numpy(), scene.capsule_b.numpy()
        length = np.linalg.norm(b - a, axis=1)
        direction = (b - a) / np.maximum(length, 1e-300)[:, None]
        direction[length == 0] = [0.0, 0.0, 1.0]
        recording.log(f"{path}/capsules", rr.Capsules3D(lengths=length, radii=scene.capsule_radius.numpy(),
                                                         translations=a, quaternions=z_to(direction),
                                                         colors=color))
    if scene.box_half.shape[0]:
        recording.log(f"{path}/boxes", rr.Boxes3D(centers=scene.box_center.numpy(), half_sizes=scene.box_half.numpy(),
                                                  quaternions=_rotation_quaternion(scene.box_rotation.numpy()),
                                                  colors=color, fill_mode="solid"))
    for i, mesh in enumerate(scene.meshes):
        recording.log(f"{path}/mesh_{i}", rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices, np.float32),
                                                    triangle_indices=np.asarray(mesh.faces, np.uint32),
                                                    albedo_factor=color))


def clearance_colors(clearance: np.ndarray, required: float) -> np.ndarray:
    """RGBA (N, 4) uint8 of clearances (N,) [m]: red < 0, orange below ``required``, green from 2·required (a
    blend between)."""
    c = np.asarray(clearance, dtype=np.float64)
    top = max(2 * required, 1e-3)
    t = np.clip((c - required) / (top - required), 0, 1)[:, None]
    colors = (1 - t) * np.array([255, 150, 0]) + t * np.array([40, 190, 60])
    colors[c < 0] = [220, 30, 30]
    return np.concatenate([colors, np.full((len(c), 1), 255)], 1).astype(np.uint8)


def log_body_clearance(recording: rr.RecordingStream, path: str, scene: Scene, points, radius, required: float,
                       ) -> None:
    """A body's points (P, 3) [m] as balls of ``radius`` (P,) [m], coloured by each ball's clearance to the scene
    (:func:`clearance_colors`), and the backbone line through them."""
    pts = torch.as_tensor(points, dtype=torch.float64)
    rad = torch.as_tensor(radius, dtype=torch.float64)
    d = scene.distances(pts)[0].amin(-1) - rad if scene.num_obstacles else torch.full_like(rad, float("inf"))
    recording.log(f"{path}/balls", rr.Points3D(pts.numpy(), radii=rad.numpy(),
                                               colors=clearance_colors(d.numpy(), required)))
    recording.log(f"{path}/backbone", rr.LineStrips3D([pts.numpy()], colors=[(60, 60, 60)], radii=0.0008))


def log_scene_solutions(recording: rr.RecordingStream, prefix: str, scene: Scene, targets, bodies, radius, success,
                        required: float) -> None:
    """An IK solve in a scene, per target b side by side along x under ``<prefix>/target_<b>``: the obstacles, the
    target frame, every solution's backbone and the first solution's body coloured by clearance. targets (B, 4, 4),
    bodies (B, K, P, 3) [m], radius (P,) [m], success (B, K), required: the clearance asked for [m]."""
    from .ik import log_ik_solutions
    poses = torch.as_tensor(targets, dtype=torch.float64)
    lines = torch.as_tensor(bodies, dtype=torch.float64)
    extent = torch.cat([lines[..., 0].flatten(), scene.sphere_center[:, 0], scene.box_center[:, 0]])
    spacing = 1.3 * float(extent.max() - extent.min()) + 0.05
    for b in range(poses.shape[0]):
        path = f"{prefix}/target_{b}"
        recording.log(path, rr.Transform3D(translation=[b * spacing, 0.0, 0.0]))
        log_obstacles(recording, f"{path}/obstacles", scene)
        log_body_clearance(recording, f"{path}/body", scene, lines[b, 0], radius, required)
    log_ik_solutions(recording, prefix, poses, lines, success, spacing=0.0)
