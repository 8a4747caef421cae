"""Constrained whole-body control of an arm carrying a continuum robot: one QP per step (qpsolvers, DAQP).

The program of :mod:`dacr_learn.deploy.qp_control` over the whole-body variables x = (θ, x_c) of a
:class:`~.composite.Composite` (tip pose and Jacobian from :meth:`Composite.kinematics`), with

- the URDF joint boxes and, with a control period ``dt`` [s], the URDF velocity limits |Δθ_i| ≤ v_i·dt as bounds;
- the robot's bend disks, length/twist boxes and optional joint speeds as for the robot alone;
- a :class:`~.control.Port`: the robot base point p_b (the flange's tool point) is kept at the port centre c as
  rows k·J_b with task k·gain·(c − p_b) of the objective (k = ``port_weight``, as :class:`~.control.WholeBodyController`
  does), and, as a hard constraint, inside the cube inscribed in the port ball: |p_b + J_b·s·z − c|_i ≤ r/√3 per
  axis (relaxed to the current offset where it is already larger, so that z = 0 stays feasible);
- clearance dampers on the robot's body and a ``scene`` in the arm's base frame (or on ``distances(x)``): the body is
  the robot's (:mod:`dacr_learn.deploy.qp_clearance`) moved by the arm; its Jacobian takes the robot's columns
  rotated into the arm's frame, R_b·∂p_c/∂x_c, and per arm joint i the velocity of the rigid motion the tip's
  Jacobian describes, v_i + ω_i × (p − p_tip). The arm's own links are not among the body points.

Float64; pure Python (no Lightning, no Rerun).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from ..body import BodyPoints, transform_body
from ..checks import F64
from ..deploy.qp_clearance import SceneLike, body_and_jacobian, clearance_rows
from ..deploy.qp_control import DistanceFn, QPConfig, QPController, Sensed
from .composite import Composite, WholeBody
from .control import Port


class WholeBodyQPController(QPController):
    """Constrained resolved-rate control of the whole body (module docstring).

    Args: model: the :class:`Composite`; config: :class:`~dacr_learn.deploy.qp_control.QPConfig` (None: the
    defaults); port: a :class:`Port` or None; distances: the clearance provider x (B, n + D) → (d (B, M) [m],
    ∂d/∂x (B, M, n + D)) or None; scene: the obstacles in the arm's base frame (a Scene, a scene YAML path or its
    dict) instead, with ``points_per_segment`` body points per segment; dt: control period [s] for the URDF
    velocity limits (None: not applied); port_weight: k > 0 of the port rows; sense: replaces the model's
    evaluation (x → :class:`Sensed` with ``base`` and ``base_jacobian``).
    ``step(q (B, n + N), target (B, 4, 4) or (B, 3), feedforward (B, 6) or (B, 3))`` → q' (B, n + N).
    """

    def __init__(self, model: Composite, config: QPConfig | None = None, port: Port | None = None,
                 distances: DistanceFn | None = None, dt: float | None = None, port_weight: float = 10.0,
                 sense: Callable[[Tensor], Sensed | tuple] | None = None, scene: SceneLike | None = None,
                 points_per_segment: int = 8):
        if not isinstance(model, Composite):
            raise ValueError(f"model: expected an arm Composite, got {type(model).__name__} (for a robot alone use "
                             f"deploy.qp_control.QPController)")
        if dt is not None and not dt > 0:
            raise ValueError(f"dt: expected > 0 [s], got {dt}")
        if not port_weight > 0:
            raise ValueError(f"port_weight: expected > 0, got {port_weight}")
        if scene is not None and not model.has_rotation:
            raise ValueError("scene: the arm's body Jacobian needs a robot with a tip rotation, got a position-only "
                             "robot model")
        self.port, self.port_weight, self.num_arm = port, port_weight, model.num_arm
        super().__init__(model, config or QPConfig(), distances, sense, scene, points_per_segment)
        self.centre = None if port is None else torch.tensor(port.centre, dtype=F64)
        if dt is not None:
            velocity = torch.as_tensor(model.arm.chain.get_joint_velocity_limits()[1], dtype=F64)
            n = self.num_arm
            self.step_bound[:n] = torch.minimum(self.step_bound[:n], velocity * dt / self.limits.scale[:n])

    def evaluate(self, x: Tensor) -> Sensed:
        kin = self.model.kinematics(x, with_base=self.port is not None)
        d, jd = (None, None) if self.distances is None else self.distances(x)
        if self.scene is not None:
            d, jd = clearance_rows(self.scene, *self.body_of(x, kin))
        base = kin.base[:, :3, 3]
        return Sensed(kin.position, kin.rotation, kin.jacobian, d, jd, base, kin.base_jacobian)

    def body_of(self, x: Tensor, kin: WholeBody) -> tuple[BodyPoints, Tensor]:
        """The robot's body in the arm's base frame at x (B, n + D) and ∂p/∂x (B, P, 3, n + D) (module docstring),
        from the whole body's kinematics ``kin`` at x."""
        n = self.num_arm
        local, jac_local = body_and_jacobian(self.model.robot, x[:, n:], self.points_per_segment)
        body = transform_body(local, kin.base)
        robot_columns = kin.base[:, None, :3, :3] @ jac_local                             # (B, P, 3, D)
        lever = (body.points - kin.position.unsqueeze(1)).unsqueeze(-1).expand(-1, -1, 3, n)
        omega = kin.jacobian[:, None, 3:, :n].expand_as(lever)
        arm_columns = kin.jacobian[:, None, :3, :n] + torch.linalg.cross(omega, lever, dim=-2)
        return body, torch.cat([arm_columns, robot_columns], dim=-1)

    def task(self, s: Sensed, target: Tensor, feedforward: Tensor | None) -> tuple[Tensor, Tensor]:
        jac, err = super().task(s, target, feedforward)
        if self.centre is None:
            return jac, err
        k = self.port_weight
        return (torch.cat([jac, k * s.base_jacobian], dim=1),
                torch.cat([err, k * self.config.gain * (self.centre - s.base)], dim=-1))

    def extra_rows(self, x: Tensor, s: Sensed) -> tuple[Tensor, Tensor] | None:
        """The port cube: ±(J_b·s)·z ≤ bound ∓ (p_b − c) per axis, bound = max(r/√3, |p_b − c|)."""
        if self.centre is None:
            return super().extra_rows(x, s)
        offset = s.base - self.centre                                                     # (B, 3)
        rows = s.base_jacobian * self.limits.scale
        bound = torch.clamp_min(offset.abs(), self.port.radius / math.sqrt(3))
        return torch.cat([rows, -rows], dim=1), torch.cat([bound - offset, bound + offset], dim=1)

    def joint_rate(self, x: Tensor) -> Tensor:
        """∂q_c/∂x (N, n + D) or (B, N, n + D) of the robot's joints (zero in the arm's columns)."""
        n = self.num_arm
        inner = super().joint_rate(x[:, n:])
        return torch.cat([inner.new_zeros(*inner.shape[:-1], n), inner], dim=-1)
