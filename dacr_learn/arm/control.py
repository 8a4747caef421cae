"""Whole-body resolved-rate control of an arm carrying a continuum robot, with every limit; and the decoupled
scheme (the arm first, then the robot) it is compared with (examples/track_port.py).

One whole-body step in the variables x = (θ, x_c) of a :class:`~.composite.Composite`, the five steps of docs/arm.md
("Whole-body resolved-rate control"): the tip task and, with a :class:`Port`, rows keeping the robot's base at the
port centre; the limits inside the step as in the IK solver; the damped least-squares step
(:func:`~dacr_learn.deploy.control.scaled_dls_step`) shortened to ``max_step`` and the URDF velocity limits; then
the admissible point nearest x + s·Δz. Everything float64; pure torch (no Lightning, no Rerun).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..checks import F64
from ..deploy.control import ControllerConfig, scaled_dls_step, tip_task
from ..ik.refine import free_jacobian
from .composite import Composite


@dataclass(frozen=True)
class Port:
    """A narrow port the robot's base point (the flange's tool point, T_a·M) must not leave: a ball of
    ``radius`` [m] around ``centre`` (3,) [m] in the arm's base frame."""

    centre: tuple[float, float, float]
    radius: float

    def __post_init__(self):
        if len(self.centre) != 3 or not self.radius > 0:
            raise ValueError(f"port: expected a centre (x, y, z) [m] and a radius > 0 [m], got {self.centre}, "
                             f"{self.radius}")


@dataclass(frozen=True)
class WholeBodyConfig(ControllerConfig):
    """gain, damping (λ [m] of the DLS), max_step: as :class:`~dacr_learn.deploy.control.ControllerConfig`;
    rotation_length: w [m/rad] (None: the robot's length); port_weight: k of the port rows;
    rest_gain: per-step pull of the variables towards a posture (the controller's ``posture``, default the
    model's rest configuration), in the null space (0: off);
    dt: control period [s] for the arm's URDF velocity limits (None: not applied)."""

    damping: float = 1e-3
    rotation_length: float | None = None
    port_weight: float = 10.0
    rest_gain: float = 0.0
    dt: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.damping is None or not self.port_weight > 0 or not self.rest_gain >= 0:
            raise ValueError(f"damping >= 0, port_weight > 0 and rest_gain >= 0 expected, got {self.damping}, "
                             f"{self.port_weight}, {self.rest_gain}")
        if self.rotation_length is not None and not self.rotation_length > 0:
            raise ValueError(f"rotation_length: expected > 0 [m/rad], got {self.rotation_length}")
        if self.dt is not None and not self.dt > 0:
            raise ValueError(f"dt: expected > 0 [s], got {self.dt}")


class WholeBodyController:
    """Resolved-rate control of the whole body (module docstring).

    :meth:`step`: joint vectors q (B, n + N), targets (B, 4, 4) poses or (B, 3) positions [m] (arm base frame),
    optional feedforward (B, 6) (Δp [m], Δφ [rad]) or (B, 3) → q' (B, n + N). ``moving`` (n + D,) bool: the
    variables this controller may change (default all). ``posture`` (n + D,): the variables ``rest_gain`` pulls
    towards (default ``model.rest``).
    """

    def __init__(self, model: Composite, config: WholeBodyConfig = WholeBodyConfig(), port: Port | None = None,
                 moving: Tensor | None = None, posture: Tensor | None = None):
        self.model, self.config, self.port = model, config, port
        self.posture = (model.rest if posture is None else posture).to(F64)
        if self.posture.shape != model.rest.shape:
            raise ValueError(f"posture: expected {tuple(model.rest.shape)} variables, got {tuple(self.posture.shape)}")
        self.limits = model.limits
        self.scale = model.limits.scale.to(F64)
        d = self.scale.shape[0]
        self.moving = torch.ones(d, dtype=torch.bool) if moving is None else moving.to(torch.bool)
        if self.moving.shape != (d,):
            raise ValueError(f"moving: expected ({d},) bools, got {tuple(self.moving.shape)}")
        self.weight = model.robot.length if config.rotation_length is None else config.rotation_length
        self.centre = None if port is None else torch.tensor(port.centre, dtype=F64)
        velocity = torch.tensor(model.arm.chain.get_joint_velocity_limits()[1], dtype=F64)
        self.max_arm_step = None if config.dt is None else velocity * config.dt       # (n,) [rad, m] per step

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        x = self.model.variables(q.to(F64))
        return self.model.joints(self.step_variables(x, target, feedforward))

    def step_variables(self, x: Tensor, target: Tensor, feedforward: Tensor | None = None,
                       rest: Tensor | None = None) -> Tensor:
        """One step in variables: x (B, n + D) → x' (B, n + D). ``rest`` (B, D_c): evaluate the robot at this
        shape instead of its own (the decoupled arm step), leaving its variables unchanged."""
        model, cfg, n = self.model, self.config, self.model.num_arm
        xe = x if rest is None else torch.cat([x[:, :n], rest], dim=-1)
        kin = model.kinematics(xe)
        rows, task = tip_task(kin.jacobian, kin.position, kin.rotation, target, feedforward, cfg.gain, self.weight)
        if self.centre is not None:
            rows.append(cfg.port_weight * kin.base_jacobian)
            task.append(cfg.port_weight * cfg.gain * (self.centre - kin.base[:, :3, 3]))
        jac, err = torch.cat(rows, dim=1), torch.cat(task, dim=-1)
        jac = jac * self.moving.to(F64)
        scaled = jac * self.scale
        scaled, free = free_jacobian(self.limits, xe, scaled, -(scaled.mT @ err.unsqueeze(-1)).squeeze(-1))
        jac = scaled / self.scale                                             # free: (B, D, D) in scaled variables
        secondary = None
        if cfg.rest_gain > 0:
            pull = cfg.rest_gain * (self.posture - xe) / self.scale * self.moving.to(F64)
            secondary = (pull.unsqueeze(1) @ free).squeeze(1)
        step = scaled_dls_step(jac, err, self.scale, cfg.damping, cfg.max_step, secondary)
        if self.max_arm_step is not None:                                     # URDF velocity limits
            ratio = (step[:, :n].abs() / self.max_arm_step).amax(-1, keepdim=True)
            step = step / ratio.clamp_min(1.0)
        moved = self.limits.project(xe + step)
        return torch.where(self.moving, moved, x)


class DecoupledController:
    """The decoupled scheme: each step, the arm's resolved-rate step for the target as if the robot were straight
    (its rest shape: the arm's own IK aims the tool, with the port), then the robot's step with the arm held.
    Same interface and limits as :class:`WholeBodyController`."""

    def __init__(self, model: Composite, config: WholeBodyConfig = WholeBodyConfig(), port: Port | None = None,
                 posture: Tensor | None = None):
        n, d = model.num_arm, model.limits.num_variables
        arm = torch.arange(d) < n
        self.model = model
        self.arm = WholeBodyController(model, config, port, moving=arm, posture=posture)
        self.robot = WholeBodyController(model, config, None, moving=~arm, posture=posture)
        self.straight = model.rest[n:].to(F64)

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        x = self.model.variables(q.to(F64))
        x = self.arm.step_variables(x, target, feedforward, rest=self.straight.expand(x.shape[0], -1))
        x = self.robot.step_variables(x, target, feedforward)
        return self.model.joints(x)
