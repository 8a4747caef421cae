"""The robot's body for the planner: backbone points, their arc lengths, and their Jacobian.

:func:`body` returns the backbone of a model's variables x (B, D): points (B, P, 3) [m] from the continuum
robot's base to its tip, in the model's base frame (the arm's base for an arm composite), and their arc lengths
(B, P) [m] from the robot's base. The analytic constant-curvature model is served here directly
(:func:`dacr_learn.kinematics.backbone_points` with the actual arc lengths, which an extensible robot changes:
the body API's are nominal), an arm composite by composing its robot's body with the arm's FK and the mount, any
other model through the body API (``model.body(x)``: a model without a body raises ValueError; a learned shape
output of K points per segment serves the largest divisor of K not above ``points_per_segment``).

:func:`body_and_jacobian` adds ∂points/∂x (B, P, 3, D) and ∂arc/∂x (B, P, D): for an arm composite the arm's
columns in closed form (pytorch-kinematics' Jacobian at the tip link, shifted to each point: v_i + ω_i × (p − p_a))
and the robot's columns rotated into the world; the robot's own columns by central differences (step 1e-6 of each
variable's scale; relative error ~1e-10: torch.func.jacfwd of the backbone measured 10× slower for these many
small operations). Float64.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..arm import Composite
from ..body import BodyPoints, transform_body
from ..checks import F64
from ..ik.adapters import ConstantCurvature, SolverModel
from ..kinematics import backbone_points, effective_features

POINTS_PER_SEGMENT = 32   # backbone points per segment of the figures (chord error of the resampled body ≤ 1e-4 L)
FD_STEP = 1e-6          # central-difference step, in units of each variable's scale


class Body(NamedTuple):
    """points (B, P, 3) [m] base → tip; arc (B, P) [m] their arc lengths from the robot's base."""

    points: Tensor
    arc: Tensor


def body(model: SolverModel, x: Tensor, points_per_segment: int = POINTS_PER_SEGMENT) -> Body:
    """The backbone of variables x (B, D) (module docstring). ValueError for a model without a body."""
    if isinstance(model, Composite):
        n = model.num_arm
        local = body(model.robot, x[:, n:], points_per_segment)
        return Body(_moved(local.points, model.base_pose(x[:, :n])), local.arc)
    if isinstance(model, ConstantCurvature):             # the actual arc lengths (an extensible robot's change)
        features = model.features(x)                                                    # (B, m, 4)
        pts = backbone_points(model.spec, features, points_per_segment)
        beta = effective_features(model.spec, features)[..., 2]                          # (B, m)
        step = (beta / points_per_segment).repeat_interleave(points_per_segment, dim=-1)
        arc = torch.cat([torch.zeros_like(beta[:, :1]), torch.cumsum(step, -1)], dim=-1)
        return Body(pts, arc)
    with torch.no_grad():            # differences, not autograd: no graph of a network's parameters
        got = model.body(x, points_per_segment)
    return Body(got.points, got.arc_length.to(F64).expand(got.points.shape[:2]))


def _moved(points: Tensor, pose: Tensor) -> Tensor:
    """Points (B, P, 3) given in a frame whose pose is ``pose`` (B, 4, 4), in the outer frame
    (:func:`dacr_learn.body.transform_body`)."""
    unused = points.new_zeros(points.shape[1])
    return transform_body(BodyPoints(points, unused, unused), pose).points


def _differences(model: SolverModel, x: Tensor, points_per_segment: int) -> tuple[Body, Tensor, Tensor]:
    """The body of x (B, D), the Jacobians of its points (B, P, 3, D) and arc lengths (B, P, D) by central
    differences."""
    b, d = x.shape
    h = FD_STEP * model.limits.scale.to(F64)
    shift = torch.diag(h)
    probe = torch.cat([x[:, None], x[:, None] + shift, x[:, None] - shift], dim=1).reshape(-1, d)
    out = body(model, probe, points_per_segment)
    pts = out.points.reshape(b, 1 + 2 * d, *out.points.shape[1:])
    arc = out.arc.reshape(b, 1 + 2 * d, -1)
    jac = (pts[:, 1:1 + d] - pts[:, 1 + d:]) / (2 * h)[None, :, None, None]                # (B, D, P, 3)
    jac_arc = (arc[:, 1:1 + d] - arc[:, 1 + d:]) / (2 * h)[None, :, None]                  # (B, D, P)
    return Body(pts[:, 0], arc[:, 0]), jac.permute(0, 2, 3, 1), jac_arc.permute(0, 2, 1)


def body_and_jacobian(model: SolverModel, x: Tensor,
                      points_per_segment: int = POINTS_PER_SEGMENT) -> tuple[Body, Tensor, Tensor]:
    """The body of x (B, D), ∂points/∂x (B, P, 3, D) and ∂arc/∂x (B, P, D) (module docstring)."""
    if not isinstance(model, Composite):
        return _differences(model, x, points_per_segment)
    n = model.num_arm
    local, jac_local, jac_arc = _differences(model.robot, x[:, n:], points_per_segment)
    jac_a, flange = model.arm.chain.jacobian_tensor(x[:, :n], ret_eef_pose=True)        # (B, 6, n), (B, 4, 4)
    base = flange @ model.mount
    rot = base[:, :3, :3]
    pts = _moved(local.points, base)
    jac_robot = torch.einsum("bij,bpjk->bpik", rot, jac_local)
    omega = jac_a[:, None, 3:].expand(-1, pts.shape[1], -1, -1)                          # (B, P, 3, n)
    rel = (pts - flange[:, None, :3, 3]).unsqueeze(-1).expand_as(omega)
    jac_arm = jac_a[:, None, :3] + torch.linalg.cross(omega, rel, dim=2)
    return (Body(pts, local.arc), torch.cat([jac_arm, jac_robot], dim=-1),
            torch.cat([torch.zeros_like(jac_arc[..., :1]).expand(-1, -1, n), jac_arc], dim=-1))
