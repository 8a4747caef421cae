"""Scenes: obstacles in one frame, from a YAML file or a dict, with batched signed distances.

Scene file (lengths [m], angles [rad]; ``rpy`` as in URDF: R = Rz(yaw)·Ry(pitch)·Rx(roll))::

    obstacles:
      - {type: sphere, center: [x, y, z], radius: r}
      - {type: capsule, a: [x, y, z], b: [x, y, z], radius: r}
      - {type: box, center: [x, y, z], half_extents: [hx, hy, hz], rpy: [roll, pitch, yaw]}
      - {type: mesh, file: part.stl, scale: 0.001, xyz: [x, y, z], rpy: [roll, pitch, yaw]}

The frame is the robot's base frame, or the arm's base frame for a robot on an arm. ``rpy`` defaults to 0,
``scale`` to 1, ``xyz`` to 0; a mesh ``file`` is relative to the scene file's folder and must be a closed
(watertight) mesh trimesh reads. Every error is one ValueError naming the file, the entry and the field.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..checks import F64
from .shapes import box_distance, capsule_distance, mesh_distance, sphere_distance

_KEYS = {"sphere": ({"center", "radius"}, set()), "capsule": ({"a", "b", "radius"}, set()),
         "box": ({"center", "half_extents"}, {"rpy"}), "mesh": ({"file"}, {"scale", "xyz", "rpy"})}


def rpy_matrix(rpy) -> Tensor:
    """URDF roll-pitch-yaw [rad] → rotation (3, 3) float64, R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    from pytorch_kinematics import transforms as tf
    return tf.euler_angles_to_matrix(torch.tensor(list(rpy)[::-1], dtype=F64), "ZYX")


@dataclass
class Scene:
    """Obstacles of a scene, float64, grouped by type; distances come in the order spheres, capsules, boxes,
    meshes (``labels`` names each, e.g. ``obstacles[2] (box)``; ``convex`` (O,) False for meshes).

    spheres: center (S, 3), radius (S,); capsules: a, b (C, 3), radius (C,); boxes: center (X, 3), rotation
    (X, 3, 3), half extents (X, 3); meshes: trimesh meshes in the scene frame [m]."""

    sphere_center: Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=F64))
    sphere_radius: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=F64))
    capsule_a: Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=F64))
    capsule_b: Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=F64))
    capsule_radius: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=F64))
    box_center: Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=F64))
    box_rotation: Tensor = field(default_factory=lambda: torch.zeros(0, 3, 3, dtype=F64))
    box_half: Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=F64))
    meshes: list = field(default_factory=list)
    labels: tuple[str, ...] = ()

    @property
    def num_obstacles(self) -> int:
        return (self.sphere_radius.numel() + self.capsule_radius.numel() + self.box_half.shape[0]
                + len(self.meshes))

    @property
    def convex(self) -> Tensor:
        """(O,) bool: True for the convex primitives (spheres, capsules, boxes), False for meshes."""
        n = self.num_obstacles - len(self.meshes)
        return torch.cat([torch.ones(n, dtype=torch.bool), torch.zeros(len(self.meshes), dtype=torch.bool)])

    def distances(self, points: Tensor, grad: bool = False) -> tuple[Tensor, Tensor | None]:
        """Signed distances (..., O) [m] of points (..., 3) to every obstacle (negative inside), differentiable in
        the points (meshes: the closest-point direction), and with ``grad`` their gradients (..., O, 3)."""
        p, parts = points.unsqueeze(-2), []
        if self.sphere_radius.numel() and not grad and not torch.is_grad_enabled():
            # no (..., O, 3) differences: torch.cdist (not under autograd: its gradient under torch.func is wrong)
            flat = points.reshape(-1, 3)
            d = torch.cdist(flat, self.sphere_center.to(flat), compute_mode="donot_use_mm_for_euclid_dist")
            parts.append(((d - self.sphere_radius.to(flat)).view(*points.shape[:-1], -1), None))
        elif self.sphere_radius.numel():
            parts.append(sphere_distance(p, self.sphere_center.to(p), self.sphere_radius.to(p), grad))
        if self.capsule_radius.numel():
            parts.append(capsule_distance(p, self.capsule_a.to(p), self.capsule_b.to(p), self.capsule_radius.to(p),
                                          grad))
        if self.box_half.shape[0] and not grad and not torch.is_grad_enabled():
            # the box frames of every point in one product: Rᵀ(p − c) = (pᵀR − cᵀR)ᵀ, no (..., O, 3) differences
            flat, rot = points.reshape(-1, 3), self.box_rotation.to(points)
            local = (flat @ rot.permute(1, 0, 2).reshape(3, -1)).view(flat.shape[0], -1, 3)
            q = local.sub_((self.box_center.to(points).unsqueeze(1) @ rot).squeeze(1)).abs_().sub_(
                self.box_half.to(points))                                        # in place: no autograd here
            d = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1).add_(q.amax(-1).clamp_max_(0.0))
            parts.append((d.view(*points.shape[:-1], -1), None))
        elif self.box_half.shape[0]:
            parts.append(box_distance(p, self.box_center.to(p), self.box_rotation.to(p), self.box_half.to(p), grad))
        for mesh in self.meshes:
            d, g = mesh_distance(points, mesh, grad)
            parts.append((d.unsqueeze(-1), None if g is None else g.unsqueeze(-2)))
        if not parts:
            return points.new_zeros(*points.shape[:-1], 0), (points.new_zeros(*points.shape[:-1], 0, 3) if grad
                                                              else None)
        if len(parts) == 1:
            return parts[0]
        return torch.cat([d for d, _ in parts], -1), (torch.cat([g for _, g in parts], -2) if grad else None)

    def pair_distances(self, points: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """Signed distance (...) [m] and gradient (..., 3) of each point (..., 3) to one obstacle each, ``index``
        (...) into the distances' order; differentiable in the points."""
        flat, idx = points.reshape(-1, 3), index.reshape(-1)
        d, g = flat.new_zeros(idx.shape[0]), flat.new_zeros(idx.shape[0], 3)
        start = 0
        groups = [(self.sphere_radius.numel(), lambda p, j: sphere_distance(
                      p, self.sphere_center.to(p)[j], self.sphere_radius.to(p)[j])),
                  (self.capsule_radius.numel(), lambda p, j: capsule_distance(
                      p, self.capsule_a.to(p)[j], self.capsule_b.to(p)[j], self.capsule_radius.to(p)[j])),
                  (self.box_half.shape[0], lambda p, j: box_distance(
                      p, self.box_center.to(p)[j], self.box_rotation.to(p)[j], self.box_half.to(p)[j]))]
        groups += [(1, lambda p, j, mesh=mesh: mesh_distance(p, mesh)) for mesh in self.meshes]
        groups = [(count, fn) for count, fn in groups if count]
        if len(groups) == 1:                                      # one kind of obstacle: no sorting out
            dd, gg = groups[0][1](flat, idx)
            return dd.view(index.shape), gg.view(*index.shape, 3)
        for count, fn in groups:
            rows = ((idx >= start) & (idx < start + count)).nonzero().squeeze(-1)
            if rows.numel():
                dd, gg = fn(flat[rows], idx[rows] - start)
                d, g = d.index_put((rows,), dd), g.index_put((rows,), gg)
            start += count
        return d.view(index.shape), g.view(*index.shape, 3)


def _fail(where: str, value: Any, expected: str):
    raise ValueError(f"{where}: got {value!r}, expected {expected}")


def _vector(where: str, value: Any, n: int = 3) -> list[float]:
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)):
        _fail(where, value, f"a list of {n} finite numbers")
    return [float(v) for v in value]


def _positive(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        _fail(where, value, "a finite number > 0")
    return float(value)


def _mesh(where: str, entry: Mapping, folder: Path):
    import trimesh
    name = entry["file"]
    if not isinstance(name, str) or not name:
        _fail(f"{where}.file", name, "the path of a mesh file (relative to the scene file)")
    path = folder / name
    if not path.is_file():
        _fail(f"{where}.file", name, f"an existing mesh file (looked for {path})")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as err:                               # trimesh raises assorted errors on bad files
        _fail(f"{where}.file", name, f"a mesh file trimesh reads ({type(err).__name__}: {err})")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or not mesh.is_watertight:
        _fail(f"{where}.file", name, "a closed (watertight) triangle mesh")
    scale = _positive(f"{where}.scale", entry.get("scale", 1.0))
    pose = torch.eye(4, dtype=F64)
    pose[:3, :3] = rpy_matrix(_vector(f"{where}.rpy", entry.get("rpy", [0, 0, 0])))
    pose[:3, 3] = torch.tensor(_vector(f"{where}.xyz", entry.get("xyz", [0, 0, 0])), dtype=F64)
    mesh = mesh.copy()
    mesh.apply_scale(scale)
    mesh.apply_transform(pose.numpy())
    return mesh


def scene_from_dict(d: Any, folder: str | Path = ".", source: str = "scene") -> Scene:
    """A :class:`Scene` from a scene description (module docstring); mesh files relative to ``folder``."""
    if not isinstance(d, Mapping) or set(d) != {"obstacles"} or not isinstance(d["obstacles"], list):
        _fail(source, d if not isinstance(d, Mapping) else sorted(d), "a mapping with one key, obstacles: a list")
    groups: dict[str, list] = {k: [] for k in _KEYS}
    for i, entry in enumerate(d["obstacles"]):
        where = f"{source}: obstacles[{i}]"
        kind = entry.get("type") if isinstance(entry, Mapping) else None
        if kind not in _KEYS:
            _fail(f"{where}.type", kind, "one of " + ", ".join(_KEYS))
        required, optional = _KEYS[kind]
        missing, unknown = required - set(entry), set(entry) - required - optional - {"type"}
        if missing or unknown:
            bad = sorted(missing or unknown)[0]
            _fail(f"{where}.{bad}", entry.get(bad, "<missing>"),
                  f"the keys {sorted(required)} (optional {sorted(optional)}) of a {kind}")
        if kind == "sphere":
            item = (_vector(f"{where}.center", entry["center"]), _positive(f"{where}.radius", entry["radius"]))
        elif kind == "capsule":
            item = (_vector(f"{where}.a", entry["a"]), _vector(f"{where}.b", entry["b"]),
                    _positive(f"{where}.radius", entry["radius"]))
        elif kind == "box":
            half = _vector(f"{where}.half_extents", entry["half_extents"])
            for j, h in enumerate(half):
                _positive(f"{where}.half_extents[{j}]", h)
            item = (_vector(f"{where}.center", entry["center"]), rpy_matrix(_vector(
                f"{where}.rpy", entry.get("rpy", [0, 0, 0]))), half)
        else:
            item = _mesh(where, entry, Path(folder))
        groups[kind].append((i, item))
    t = lambda rows, j: torch.tensor([r[1][j] for r in rows], dtype=F64)  # noqa: E731
    s, c, b, m = groups["sphere"], groups["capsule"], groups["box"], groups["mesh"]
    scene = Scene(meshes=[r[1] for r in m])
    if s:
        scene.sphere_center, scene.sphere_radius = t(s, 0), t(s, 1)
    if c:
        scene.capsule_a, scene.capsule_b, scene.capsule_radius = t(c, 0), t(c, 1), t(c, 2)
    if b:
        scene.box_center, scene.box_half = t(b, 0), t(b, 2)
        scene.box_rotation = torch.stack([r[1][1] for r in b])
    scene.labels = tuple(f"obstacles[{i}] ({k})" for k, rows in groups.items() for i, _ in rows)
    return scene


def load_scene(scene: str | Path | Mapping | Scene) -> Scene:
    """A :class:`Scene` from a scene YAML path, a dict (mesh files relative to the working folder) or a Scene."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, Mapping):
        return scene_from_dict(scene)
    if not isinstance(scene, (str, Path)):
        raise ValueError(f"scene: expected a Scene, the path of a scene YAML file or its dict, "
                         f"got {type(scene).__name__}")
    from ..checks import read_yaml
    data = read_yaml(scene, "a scene in YAML (obstacles: [...], see docs/body.md)")
    return scene_from_dict(data, Path(scene).parent, str(scene))
