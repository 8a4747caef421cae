"""Constrained whole-body control of an arm carrying a continuum robot: one QP per step (qpsolvers, DAQP).

The program of :mod:`dacr_learn.deploy.qp_control` over the whole-body variables x = (θ, x_c) of a
:class:`~.composite.Composite` (tip pose and Jacobian from :meth:`Composite.kinematics`), with

- the URDF joint boxes and, with a control period ``dt`` [s], the URDF velocity limits |Δθ_i| ≤ v_i·dt as bounds;
- the robot's bend disks, length/twist boxes and optional joint speeds as for the robot alone;
- a :class:`~.control.Port`: the robot base point p_b (the flange's tool point) is kept at the port centre c as
  rows k·J_b with task k·gain·(c − p_b) of the objective (k = ``port_weight``, as :class:`~.control.WholeBodyController`
  does), and, as a hard constraint, inside the cube inscribed in the port ball: |p_b + J_b·s·z − c|_i ≤ r/√3 per
  axis (relaxed to the current offset where it is already larger, so that z = 0 stays feasible);
- clearance dampers on ``distances(x)``: the body (robot and, if the provider includes them, the arm's links) to the
  obstacles, in the arm's base frame.

Float64; pure Python (no Lightning, no Rerun).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ..checks import F64
from ..deploy.qp_control import DistanceFn, QPConfig, QPController, Sensed
from .composite import Composite
from .control import Port


class WholeBodyQPController(QPController):
    """Constrained resolved-rate control of the whole body (module docstring).

    Args: model: the :class:`Composite`; config: :class:`~dacr_learn.deploy.qp_control.QPConfig` (None: the
    defaults); port: a
    :class:`Port` or None; distances: the clearance provider x (B, n + D) → (d (B, M) [m], ∂d/∂x (B, M, n + D)) or
    None; dt: control period [s] for the URDF velocity limits (None: not applied); port_weight: k > 0 of the port
    rows; sense: replaces the model's evaluation (x → :class:`Sensed` with ``base`` and ``base_jacobian``).
    ``step(q (B, n + N), target (B, 4, 4) or (B, 3), feedforward (B, 6) or (B, 3))`` → q' (B, n + N).
    """

    def __init__(self, model: Composite, config: QPConfig | None = None, port: Port | None = None,
                 distances: DistanceFn | None = None, dt: float | None = None, port_weight: float = 10.0,
                 sense: Callable[[Tensor], Sensed | tuple] | None = None):
        if not isinstance(model, Composite):
            raise ValueError(f"model: expected an arm Composite, got {type(model).__name__} (for a robot alone use "
                             f"deploy.qp_control.QPController)")
        if dt is not None and not dt > 0:
            raise ValueError(f"dt: expected > 0 [s], got {dt}")
        if not port_weight > 0:
            raise ValueError(f"port_weight: expected > 0, got {port_weight}")
        super().__init__(model, config or QPConfig(), distances, sense)
        self.port, self.port_weight, self.num_arm = port, port_weight, model.num_arm
        self.centre = None if port is None else torch.tensor(port.centre, dtype=F64)
        if dt is not None:
            velocity = np.asarray(model.arm.chain.get_joint_velocity_limits()[1], dtype=float)
            n = self.num_arm
            self.step_bound[:n] = np.minimum(self.step_bound[:n], velocity * dt / self.scale[:n])

    def sense(self, x: Tensor) -> Sensed:
        if self.custom_sense is not None:
            return super().sense(x)
        kin = self.model.kinematics(x, with_base=self.port is not None)
        d, jd = (None, None) if self.distances is None else self.distances(x)
        base = kin.base[:, :3, 3]
        return Sensed(kin.position, kin.rotation, kin.jacobian, d, jd, base, kin.base_jacobian)

    def task(self, s: Sensed, target: Tensor, feedforward: Tensor | None) -> tuple[Tensor, Tensor]:
        jac, err = super().task(s, target, feedforward)
        if self.centre is None:
            return jac, err
        k = self.port_weight
        return (torch.cat([jac, k * s.base_jacobian], dim=1),
                torch.cat([err, k * self.config.gain * (self.centre - s.base)], dim=-1))

    def extra_rows(self, x: np.ndarray, s: Sensed, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The port cube: ±(J_b·s)·z ≤ bound ∓ (p_b − c) per axis, bound = max(r/√3, |p_b − c|)."""
        if self.centre is None:
            return super().extra_rows(x, s, b)
        offset = (s.base[b] - self.centre).numpy()
        rows = s.base_jacobian[b].numpy() * self.scale
        bound = np.maximum(self.port.radius / math.sqrt(3), np.abs(offset))
        return np.concatenate([rows, -rows]), np.concatenate([bound - offset, bound + offset])

    def joint_rate(self, x: np.ndarray) -> np.ndarray:
        """∂q_c/∂x (N, n + D) of the robot's joints (zero in the arm's columns)."""
        n = self.num_arm
        inner = super().joint_rate(x[n:])
        return np.concatenate([np.zeros((inner.shape[0], n)), inner], axis=1)
