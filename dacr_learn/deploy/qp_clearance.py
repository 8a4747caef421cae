"""Clearance rows of the QP controllers: a model's body, its Jacobian and a scene's closed-form distances.

For variables x (B, D) of a model with a body (:meth:`~dacr_learn.ik.SolverModel.body`: points p_j (B, P, 3) [m],
envelope radius a_j (P,) [m]) and a :class:`~dacr_learn.scene.Scene` of O obstacles, the clearance of point j to
obstacle k and its Jacobian are

    d_jk = f_k(p_j) − a_j                 [m]  (f_k: the scene's signed distance, negative inside)
    ∂d_jk/∂x = ∇f_k(p_j)ᵀ · ∂p_j/∂x        (1, D)

with ∇f_k in closed form for spheres, capsules and boxes (the unit direction away from the nearest surface point;
meshes: the closest-point direction, :meth:`Scene.distances`) and ∂p/∂x (B, P, 3, D):

- the analytic model (:class:`~dacr_learn.ik.ConstantCurvature`), in closed form together with the tip
  (:func:`cc_body_and_jacobian`): body point j of segment k at the fraction t of it is the tip of a virtual robot
  whose segments before k are the robot's, segment k has features (t·ρ, t·β, α) and later segments are straight
  and of length 0 (the identity); one call of :func:`~dacr_learn.kinematics.cc_pose_and_jacobian` on the P − 1
  virtual robots (every segment extending, so that β = t·l also for a fixed-length segment) gives every point and
  its Jacobian, ∂p_j/∂x_i = ∂p_j/∂f'_i · t_ji (the virtual feature f'_i = t_ji·f_i), the last point's full 6-row
  Jacobian being the tip's;
- any other model with a differentiable body: forward-mode automatic differentiation of its body
  (:func:`torch.func.jacfwd`; eager only, slow for an op-heavy body);
- an arm composite: the robot's, composed with the arm's in :mod:`dacr_learn.arm.qp_control`.

Float64; no Lightning, no Rerun.
"""
from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..body import BodyPoints, body_layout
from ..ik.adapters import ConstantCurvature, TipJacobian
from ..kinematics import cc_pose_and_jacobian, effective_features
from ..models import FEATURE_COLUMNS, actuated_columns
from ..robot import RobotSpec
from ..scene import Scene

SceneLike = Scene | str | Path | dict[str, Any]
"""A scene: a :class:`Scene`, the path of a scene YAML file (docs/body.md) or its dict."""


@functools.lru_cache(maxsize=16)
def _virtual(spec: RobotSpec, points_per_segment: int) -> tuple[RobotSpec, np.ndarray, list[tuple[int, int]],
                                                                 np.ndarray]:
    """The virtual robots of the module docstring: their spec (every segment extending), the multipliers W
    (m·K, m, 4) of the features, the actuated (segment, column) pairs and t_ji (m·K, D). Arrays, not tensors: a
    cached tensor made while torch.export traces a call would be a fake one in later eager calls."""
    extend = {"0": "I", "II": "III"}
    virtual = dataclasses.replace(spec, segments=tuple(dataclasses.replace(s, type=extend.get(s.type, s.type))
                                                       for s in spec.segments))
    m, k = spec.num_segments, points_per_segment
    weight = np.zeros((m * k, m, 4))
    for seg in range(m):
        for j in range(k):
            row = weight[seg * k + j]
            row[:seg] = 1.0
            row[seg, :3], row[seg, 3] = (j + 1) / k, 1.0
    columns = [(seg, FEATURE_COLUMNS.index(name)) for seg, name in actuated_columns(spec)]
    chain = weight[:, [c[0] for c in columns], [c[1] for c in columns]]
    return virtual, weight, columns, chain


def cc_body_and_jacobian(model: ConstantCurvature, x: Tensor, points_per_segment: int
                         ) -> tuple[TipJacobian, BodyPoints, Tensor]:
    """Tip (:class:`~dacr_learn.ik.adapters.TipJacobian`), body (P = 1 + m·K points) and ∂p/∂x (B, P, 3, D) of the
    analytic model at x (B, D), in closed form from one kinematics call (module docstring)."""
    virtual, weight, columns, chain = _virtual(model.spec, points_per_segment)
    features = effective_features(model.spec, model.features(x))                  # (B, m, 4)
    virtual_features = features.unsqueeze(1) * torch.from_numpy(weight).to(x)        # (B, m·K, m, 4)
    pose, jac = cc_pose_and_jacobian(virtual, virtual_features, columns)             # (B, m·K, 4, 4), (…, 6, D)
    jac = jac * torch.from_numpy(chain).to(x).unsqueeze(1)
    points = torch.cat([torch.zeros_like(pose[:, :1, :3, 3]), pose[:, :, :3, 3]], 1)
    point_jac = torch.cat([torch.zeros_like(jac[:, :1, :3]), jac[:, :, :3]], 1)
    body = BodyPoints(points, *body_layout(model.spec, points_per_segment, x.dtype, x.device))
    return TipJacobian(pose[:, -1, :3, 3], pose[:, -1, :3, :3], jac[:, -1]), body, point_jac


def tip_and_body(model, x: Tensor, points_per_segment: int) -> tuple[TipJacobian, BodyPoints, Tensor]:
    """Tip, body and ∂p/∂x (B, P, 3, D) of a model at x (B, D): :func:`cc_body_and_jacobian` for the analytic
    model, else its ``tip_and_jacobian`` and :func:`body_and_jacobian`."""
    if isinstance(model, ConstantCurvature):
        return cc_body_and_jacobian(model, x, points_per_segment)
    return (model.tip_and_jacobian(x), *body_and_jacobian(model, x, points_per_segment))


def body_and_jacobian(model, x: Tensor, points_per_segment: int) -> tuple[BodyPoints, Tensor]:
    """The model's body at x (B, D) and the Jacobian ∂p/∂x (B, P, 3, D) of its points: closed form for the
    analytic model, else forward-mode differentiation of :meth:`model.body` (ValueError for a model without a
    body)."""
    if isinstance(model, ConstantCurvature):
        return cc_body_and_jacobian(model, x, points_per_segment)[1:]
    def points(v: Tensor) -> tuple[Tensor, Tensor]:
        p = model.body(v.unsqueeze(0), points_per_segment).points[0]
        return p, p

    if x.dim() != 2:
        raise ValueError(f"x: expected (B, D) variables, got {tuple(x.shape)}")
    body = model.body(x[:1], points_per_segment)                       # the layout (and the no-body error)
    jac, pts = torch.func.vmap(torch.func.jacfwd(points, has_aux=True))(x)
    return BodyPoints(pts, body.arc_length, body.radius), jac


def clearance_rows(scene: Scene, body: BodyPoints, jacobian: Tensor) -> tuple[Tensor, Tensor]:
    """Clearances d (B, P·O) [m] of every (body point, obstacle) pair (point-major) and their Jacobians
    ∂d/∂x (B, P·O, D) (module docstring), from the body (points (B, P, 3), radius (P,)) and ∂p/∂x (B, P, 3, D)."""
    d, grad = scene.distances(body.points, grad=True)                                 # (B, P, O), (B, P, O, 3)
    d = d - body.radius.to(d).unsqueeze(-1)
    jd = (grad.unsqueeze(-1) * jacobian.unsqueeze(2)).sum(-2)                          # (B, P, O, D)
    return d.flatten(1), jd.flatten(1, 2)

