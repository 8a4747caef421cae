"""Obstacles and clearance: scene files, batched signed distances, swept-body clearance bounds (docs/body.md)."""
from .clearance import (
           Swept,
           capsule_chain,
           capsule_clearance,
           capsule_pair,
           chain_clearance,
           convex_bound,
           cut_bound,
           join,
           swept_body,
           swept_clearance,
)
from .files import Scene, load_scene, rpy_matrix, scene_from_dict
from .shapes import box_distance, capsule_distance, mesh_distance, sphere_distance

__all__ = ["Scene", "Swept", "box_distance", "capsule_chain", "capsule_clearance", "capsule_distance", "capsule_pair",
           "chain_clearance", "convex_bound", "cut_bound", "join", "load_scene", "mesh_distance", "rpy_matrix",
           "scene_from_dict", "sphere_distance", "swept_body", "swept_clearance"]
