"""Collision geometry of an arm's links as capsules in the link frames (for clearance checks, docs/body.md).

From the URDF's ``<collision>`` elements of the chain's links, each made a capsule that contains it:
a sphere is a capsule of zero length; a cylinder (axis z, ``length``, ``radius``) the capsule of the same axis
segment and radius (its ends rounded: up to ``radius`` longer); a box the capsule along its longest axis whose
radius is the diagonal of the other two half extents; a mesh (read by trimesh when its file resolves, relative
to the URDF's folder, ``package://`` stripped) the capsule of its oriented bounding box, scaled. A link whose
mesh does not resolve gets the fallback. When no link of the chain has a ``<collision>`` element (e.g. a
kinematics-only URDF), every link gets the fallback: a capsule of radius :data:`FALLBACK_LINK_RADIUS` from its
frame origin to the next frame's origin (consecutive origins that coincide give none).

Near the mount: the robot's base sits on the tip link, so robot–arm self-collision ignores the geometry of the
tip link and of every link from the child link of the last movable joint to the tip (on a Panda flange:
panda_link7 and panda_link8); those links are still checked against the scene's obstacles.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from ..checks import F64

FALLBACK_LINK_RADIUS = 0.06   # [m], about the radius of a Panda link's casing


class LinkCapsules(NamedTuple):
    """Capsules on an arm's links: ``frame`` (C,) index into the arm's ``frame_names``; a, b (C, 3) [m] the axis
    ends in that frame; radius (C,) [m]; near_mount (C,) bool (not checked against the robot); ``source``: "urdf"
    or "fallback"."""

    frame: Tensor
    a: Tensor
    b: Tensor
    radius: Tensor
    near_mount: Tensor
    source: str


def _pose(origin) -> Tensor:
    from ..scene import rpy_matrix
    pose = torch.eye(4, dtype=F64)
    if origin is not None:
        if origin.rpy is not None:
            pose[:3, :3] = rpy_matrix([float(v) for v in origin.rpy])
        if origin.xyz is not None:
            pose[:3, 3] = torch.tensor([float(v) for v in origin.xyz], dtype=F64)
    return pose


def _box_capsule(pose: Tensor, half: Tensor) -> tuple[Tensor, Tensor, float]:
    axis = int(torch.argmax(half))
    others = [i for i in range(3) if i != axis]
    end = torch.zeros(3, dtype=F64)
    end[axis] = half[axis]
    a, b = pose[:3, :3] @ -end + pose[:3, 3], pose[:3, :3] @ end + pose[:3, 3]
    return a, b, float(torch.linalg.vector_norm(half[others]))


def _mesh_capsule(geometry, pose: Tensor, folder: Path):
    import trimesh
    name = str(geometry.filename or "")
    path = folder / (name.split("://", 1)[1].split("/", 1)[-1] if "://" in name else name)
    if not name or not path.is_file():
        return None
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception:                                   # an unreadable mesh: the link takes the fallback
        return None
    scale = geometry.scale if geometry.scale is not None else [1.0, 1.0, 1.0]
    mesh.apply_scale([float(s) for s in scale] if len(scale) == 3 else float(scale[0]))
    box = mesh.bounding_box_oriented
    box_pose = pose @ torch.as_tensor(box.primitive.transform, dtype=F64)
    return _box_capsule(box_pose, torch.as_tensor(box.primitive.extents, dtype=F64) / 2)


def _element_capsule(collision, folder: Path):
    from pytorch_kinematics.urdf_parser_py.urdf import Box, Cylinder, Mesh, Sphere
    geom, pose = collision.geometry, _pose(collision.origin)
    if isinstance(geom, Sphere):
        return pose[:3, 3], pose[:3, 3], float(geom.radius)
    if isinstance(geom, Cylinder):
        end = pose[:3, 2] * float(geom.length) / 2
        return pose[:3, 3] - end, pose[:3, 3] + end, float(geom.radius)
    if isinstance(geom, Box):
        return _box_capsule(pose, torch.tensor([float(s) / 2 for s in geom.size], dtype=F64))
    if isinstance(geom, Mesh):
        return _mesh_capsule(geom, pose, folder)
    return None


def link_capsules(urdf_robot, chain, frame_names: tuple[str, ...], folder: Path) -> LinkCapsules:
    """The capsules (module docstring) of the links ``frame_names`` (root to tip) of a parsed URDF
    (pytorch-kinematics' ``URDF``) and its float64 serial ``chain``; meshes relative to ``folder``."""
    links = {link.name: link for link in urdf_robot.links}
    movable = [i for i, n in enumerate(frame_names) if chain.find_frame(n).joint.joint_type != "fixed"]
    first_near = movable[-1] if movable else len(frame_names) - 1
    rows, fallback_links = [], []
    any_collision = any(links[n].collisions for n in frame_names if n in links)
    for i, name in enumerate(frame_names):
        elements = links[name].collisions if name in links else []
        capsules = [_element_capsule(c, folder) for c in elements]
        if not any_collision or any(c is None for c in capsules):
            fallback_links.append(i)
            continue
        rows += [(i, *c) for c in capsules]
    for i in fallback_links:
        if i + 1 < len(frame_names):
            offset = chain.find_frame(frame_names[i + 1]).joint.offset.get_matrix()[0, :3, 3].to(F64)
            if float(torch.linalg.vector_norm(offset)) > 1e-9:
                rows.append((i, torch.zeros(3, dtype=F64), offset, FALLBACK_LINK_RADIUS))
    rows.sort(key=lambda r: r[0])
    if not rows:
        empty = torch.zeros(0, 3, dtype=F64)
        return LinkCapsules(torch.zeros(0, dtype=torch.long), empty, empty, torch.zeros(0, dtype=F64),
                            torch.zeros(0, dtype=torch.bool), "urdf" if any_collision else "fallback")
    frame = torch.tensor([r[0] for r in rows], dtype=torch.long)
    return LinkCapsules(frame, torch.stack([torch.as_tensor(r[1], dtype=F64) for r in rows]),
                        torch.stack([torch.as_tensor(r[2], dtype=F64) for r in rows]),
                        torch.tensor([r[3] for r in rows], dtype=F64), frame >= first_near,
                        "urdf" if any_collision and not fallback_links else "fallback")


def posed_capsules(capsules: LinkCapsules, frames: Tensor) -> tuple[Tensor, Tensor]:
    """Capsule ends (B, C, 3) [m] in the arm's base frame from the chain's frame poses (B, F, 4, 4)."""
    pose = frames[:, capsules.frame]                                          # (B, C, 4, 4)
    move = lambda p: (pose[..., :3, :3] @ p.to(pose).unsqueeze(-1)).squeeze(-1) + pose[..., :3, 3]  # noqa: E731
    return move(capsules.a), move(capsules.b)

