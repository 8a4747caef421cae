"""Resolved-rate (damped least-squares) task-space position control in Clarke space (docs/export.md,
"Resolved-rate controller", describes each step).

One step from the commanded joint vector q (..., N) [m, rad] to a tip target p* [m]: (pose, J_f, J_q) =
jacobian(q); Δx = feedforward + gain·(p* − p); Δz = J̃ᵀ(J̃J̃ᵀ + λ²I)⁻¹Δx in scaled features z = f / s, ‖Δz‖ ≤ max_step;
f' = sat(f + s·Δz); q' = dec(f'), so every command satisfies the displacement constraint. Float64; pure torch.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from pytorch_kinematics.transforms import matrix_to_axis_angle
from torch import Tensor

from ..checks import F64, to_f64
from ..clarke_space import ClarkeSpace
from ..kinematics import cc_pose_and_jacobian
from ..models import actuated_to_features
from ..robot import RobotSpec

JacobianFn = Callable[[Tensor], tuple[Tensor, Tensor, Tensor]]


@dataclass(frozen=True)
class ControllerConfig:
    """The settings every resolved-rate controller shares (:func:`scaled_dls_step`): gain: fraction of the task
    error corrected per step, in (0, 1]; damping: λ [task unit] of the damped least squares (None: the
    controller's own default; here 1 % of the robot length); max_step: largest scaled step ‖Δz‖ per control
    step (1 = a variable's whole half-range). The arm's and the servo controllers' configs extend it
    (:class:`~dacr_learn.arm.WholeBodyConfig`, :class:`~dacr_learn.hardware.deploy.control.ServoControl`)."""

    gain: float = 0.5
    damping: float | None = None
    max_step: float = 0.05

    def __post_init__(self):
        if not 0 < self.gain <= 1:
            raise ValueError(f"gain: expected a value in (0, 1], got {self.gain}")
        if self.damping is not None and not self.damping >= 0:
            raise ValueError(f"damping: expected >= 0 [m], got {self.damping}")
        if not self.max_step > 0:
            raise ValueError(f"max_step: expected > 0, got {self.max_step}")


class ResolvedRateController:
    """Damped least-squares position controller in Clarke space (the module docstring) of the robot ``spec``:
    ``jacobian`` q (..., N) → (pose (..., 4, 4), J_f (..., 6, D), J_q), e.g. ``dacr_learn.export.load(export_dir,
    "jacobian")`` or :func:`analytic_jacobian`; ``config``: gains and limits (:class:`ControllerConfig`)."""

    def __init__(self, spec: RobotSpec, jacobian: JacobianFn, config: ControllerConfig = ControllerConfig()):
        self.spec, self.jacobian, self.config = spec, jacobian, config
        self.space = ClarkeSpace(spec)
        self.damping = 0.01 * spec.total_length if config.damping is None else config.damping

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None,
             measured: Tensor | None = None) -> Tensor:
        """One control step: commanded q (..., N), target (..., 3) [m] → next command q' (..., N), float64.

        ``feedforward`` (..., 3) [m]: the target's displacement over this step (velocity × dt);
        ``measured`` (..., 3) [m]: the measured tip position (else the learned FK's is used).
        """
        q = to_f64(q)
        pose, jac_f, _ = self.jacobian(q)
        position = to_f64(pose[..., :3, 3] if measured is None else measured)
        task = self.config.gain * (to_f64(target) - position)
        if feedforward is not None:
            task = task + to_f64(feedforward)
        limits = self.space.limits
        step = scaled_dls_step(jac_f[..., :3, :], task, limits.scale, self.damping, self.config.max_step)  # Δf
        return self.space.joints(limits.project(self.space.features(q) + step))


def scaled_dls_step(jac: Tensor, task_step: Tensor, scale: Tensor, damping: float, max_step: float,
                    secondary: Tensor | None = None) -> Tensor:
    """Damped least-squares step in scaled coordinates z = u / s, for any actuation vector u (float64).

    J (..., k, D) [task unit per u unit], Δx (..., k), s (D,) [u units], λ = damping [task unit] →
    Δu = s·Δz, Δz = J̃ᵀ(J̃J̃ᵀ + λ²I)⁻¹Δx with J̃ = J·diag(s), shortened to ‖Δz‖ ≤ max_step.

    ``secondary`` (..., D): a step Δz₂ [scaled units] wanted for a second task (e.g. pulling the commands
    towards a rest posture), added through the damped null-space projector: Δz += (I − J̃ᵀ(J̃J̃ᵀ + λ²I)⁻¹J̃)Δz₂
    (with λ = 0 it does not move the task: J̃·projected Δz₂ = 0). Directions J does not see at all
    (a slack tendon's zero column) pass unchanged, so this is how a resolved-rate controller re-tensions a
    tendon its Jacobian cannot. The sum is shortened to ``max_step``.
    """
    j = to_f64(jac) * to_f64(scale)                                               # J̃ = J·diag(s)
    a = j @ j.mT + damping**2 * torch.eye(j.shape[-2], dtype=F64)
    rhs = to_f64(task_step).unsqueeze(-1)
    if secondary is not None:
        if tuple(secondary.shape) != tuple(j.shape[:-2]) + (j.shape[-1],):
            raise ValueError(f"secondary: expected shape {tuple(j.shape[:-2]) + (j.shape[-1],)} (a scaled step per "
                             f"actuator), got {tuple(secondary.shape)}")
        z2 = to_f64(secondary).unsqueeze(-1)
        rhs = rhs - j @ z2                                                    # Δz = z₂ + J̃ᵀA⁻¹(Δx − J̃z₂)
    dz = (j.mT @ torch.linalg.solve(a, rhs)).squeeze(-1)
    if secondary is not None:
        dz = dz + to_f64(secondary)
    norm = torch.linalg.vector_norm(dz, dim=-1, keepdim=True)
    dz = dz * torch.clamp(max_step / norm.clamp_min(1e-300), max=1.0)
    return dz * to_f64(scale)


def tip_task(jacobian: Tensor, position: Tensor, rotation: Tensor | None, target: Tensor,
             feedforward: Tensor | None, gain: float, weight: float) -> tuple[list[Tensor], list[Tensor]]:
    """The tip task of a resolved-rate step, as lists of rows a controller may add to: from the tip ``position``
    (B, 3) [m], ``rotation`` (B, 3, 3) or None and its Jacobian (B, 6 or 3, D) towards ``target`` (B, 4, 4) poses
    or (B, 3) positions [m]: rows J_v [and w·J_ω], task gain·(p* − p) [and gain·w·log(R*Rᵀ)], w = ``weight``
    [m/rad] (a rotation error counts like a length), plus the ``feedforward`` (B, 6) (Δp [m], Δφ [rad]) or (B, 3).
    Returns ([J_v, w·J_ω], [e_v, e_ω]) (the rotation entries for a pose target only). ValueError for a pose
    target on a position-only model or a feedforward of the wrong width."""
    target = target.to(F64)
    pose = target.dim() == 3
    rows, task = [jacobian[:, :3]], [gain * ((target[:, :3, 3] if pose else target) - position)]
    if pose:
        if rotation is None or jacobian.shape[1] < 6:
            raise ValueError("target: this model gives a tip position only; pass (B, 3) positions")
        rows.append(weight * jacobian[:, 3:6])
        task.append(gain * weight * matrix_to_axis_angle(target[:, :3, :3] @ rotation.mT))
    if feedforward is not None:
        ff = feedforward.to(F64)
        if ff.shape[-1] != (6 if pose else 3):
            raise ValueError(f"feedforward: expected (B, {6 if pose else 3}) for this target, got {tuple(ff.shape)}")
        task = [task[0] + ff[:, :3]] + ([task[1] + weight * ff[:, 3:6]] if pose else [])
    return rows, task


def analytic_jacobian(spec: RobotSpec) -> JacobianFn:
    """Model-based reference for the controller: q (..., N) → (pose, J_f, J_q) of the analytic
    constant-curvature FK (float64; J_f in closed form, :func:`~dacr_learn.kinematics.cc_pose_and_jacobian`, and
    J_q = J_f·∂f/∂q of the encoder; for comparisons and tests, not for kHz loops)."""
    space = ClarkeSpace(spec)

    def jacobian(q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        lead = q.shape[:-1]
        q2 = q.to(F64).reshape(-1, spec.num_joints)
        u = space.fold.inputs(q2)
        features = actuated_to_features(space.fold.features(u), space.selection, space.base)
        pose, jac = cc_pose_and_jacobian(spec, features)                         # J (B, 6, m, 4)
        jac_f = jac.flatten(-2) @ space.selection.mT                             # the actuated columns (B, 6, D)
        jac_q = jac_f @ space.fold.jacobian(q2, u)
        return (pose.reshape(*lead, 4, 4), jac_f.reshape(*lead, *jac_f.shape[-2:]),
                jac_q.reshape(*lead, *jac_q.shape[-2:]))
    return jacobian
