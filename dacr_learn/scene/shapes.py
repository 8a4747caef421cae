"""Signed distances of points to obstacles, batched and differentiable (negative inside).

Closed forms for spheres, capsules and boxes (torch, differentiable by autograd); each also returns its
gradient in closed form (the unit direction away from the nearest surface point), which the collision bounds
of :mod:`.clearance` use. Meshes go through trimesh (closest points on the triangles, the inside test by ray
casting): not differentiable through the library, so :class:`MeshDistance` gives the gradient of the closest-point
direction. Each function takes points (..., 3) [m] and obstacle parameters that broadcast with them (e.g. (O, 3) against
points (..., 1, 3) for every pair, or one obstacle per point), and returns distances (...) [m] and, with
``grad``, gradients (..., 3) (else None).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

_TINY = 1e-300


def _norm(v: Tensor, grad: bool) -> tuple[Tensor, Tensor | None]:
    n = torch.linalg.vector_norm(v, dim=-1)
    return n, (v / n.clamp_min(_TINY).unsqueeze(-1) if grad else None)


def sphere_distance(points: Tensor, center: Tensor, radius: Tensor, grad: bool = True):
    """Points (..., 3) to spheres: center (..., 3), radius (...) [m]."""
    n, g = _norm(points - center, grad)
    return n - radius, g


def capsule_distance(points: Tensor, a: Tensor, b: Tensor, radius: Tensor, grad: bool = True):
    """Points (..., 3) to capsules (the segment a–b swept by a ball of ``radius``): a, b (..., 3), radius (...)."""
    ab = b - a
    t = (((points - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(_TINY)).clamp(0.0, 1.0)
    n, g = _norm(points - (a + t.unsqueeze(-1) * ab), grad)
    return n - radius, g


def box_distance(points: Tensor, center: Tensor, rotation: Tensor, half: Tensor, grad: bool = True):
    """Points (..., 3) to boxes: center (..., 3), rotation (..., 3, 3) (the box axes in the points' frame), half
    extents (..., 3) [m]."""
    local = ((points - center).unsqueeze(-2) @ rotation).squeeze(-2)                  # Rᵀ(p − c)
    q = local.abs() - half
    outside, g_out = _norm(q.clamp_min(0.0), grad)
    inner = q.max(-1)
    d = outside + inner.values.clamp_max(0.0)
    if not grad:
        return d, None
    g_in = torch.nn.functional.one_hot(inner.indices, 3).to(q.dtype)
    g_local = torch.where((outside > 0).unsqueeze(-1), g_out, g_in) * torch.where(local < 0, -1.0, 1.0)
    return d, (rotation @ g_local.unsqueeze(-1)).squeeze(-1)


class MeshDistance(torch.autograd.Function):
    """Signed distance (..., ) of points (..., 3) to one closed triangle mesh (trimesh), negative inside; its
    gradient is the unit direction from the closest surface point (flipped inside)."""

    @staticmethod
    def forward(points: Tensor, mesh) -> tuple[Tensor, Tensor]:
        import trimesh
        flat = points.detach().reshape(-1, 3).cpu().numpy().astype(np.float64)
        closest, dist, _ = trimesh.proximity.closest_point(mesh, flat)
        sign = np.where(mesh.contains(flat), -1.0, 1.0)
        direction = (flat - closest) / np.maximum(dist, _TINY)[:, None] * sign[:, None]
        to = lambda x, *s: torch.as_tensor(x, dtype=points.dtype, device=points.device).reshape(*s)  # noqa: E731
        return to(sign * dist, *points.shape[:-1]), to(direction, *points.shape)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(output[1])
        ctx.mark_non_differentiable(output[1])

    @staticmethod
    def backward(ctx, grad_d, grad_g):
        (direction,) = ctx.saved_tensors
        return grad_d.unsqueeze(-1) * direction, None


def mesh_distance(points: Tensor, mesh, grad: bool = True):
    """Points (..., 3) to one closed trimesh mesh (in the points' frame)."""
    d, g = MeshDistance.apply(points, mesh)
    return d, (g if grad else None)
