"""Resolved-rate control of an exported hardware model in servo space: servo commands [mm] → tip, run causally.

Each step (docs/export.md, "Driving a controller with it"): the exported ``jacobian`` (J = ∂tip/∂servo [m/mm])
along the plant's last step (the sliding derivative: the one-sided reversal derivative made the loop diverge on a
strongly history-dependent model), a damped least-squares step (:func:`dacr_learn.deploy.control.scaled_dls_step`)
clipped to the training box; opt-in, a null-space task re-tensions slack servos (:func:`slack_pull`).

:func:`initial_command` (the IK solution nearest the current command) and :func:`run_control` (track targets with
a plant and a Jacobian) are the tasks; examples/control_hardware_model.py runs them on an export.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ...checks import F64
from ...deploy import export as dexport
from ...deploy.control import ControllerConfig, scaled_dls_step
from ...ik import IKOptions, solve_ik
from .checkpoint import HardwareModel

__all__ = ["ServoControl", "initial_command", "load_hardware_export", "run_control", "servo_signs", "slack_pull"]


@dataclass(frozen=True)
class ServoControl(ControllerConfig):
    """gain, damping (λ [m]), max_step (largest scaled servo step ‖Δu / s‖, s: each servo's half-range): as
    :class:`~dacr_learn.deploy.control.ControllerConfig`; retension: scaled step in [0, max_step] pulling each slack
    servo (zero column of J) in, in J's null space (0: off; docs/export.md: a trade-off).
    """

    damping: float = 2e-3
    retension: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.damping is None:
            raise ValueError("damping: expected >= 0 [m], got None")
        if not 0 <= self.retension <= self.max_step:
            raise ValueError(f"retension: expected a value in [0, max_step = {self.max_step}], got {self.retension}")


def initial_command(model: HardwareModel, target: Tensor, current: Tensor, solutions: int = 4,
                    options: IKOptions | None = None) -> tuple[Tensor, float]:
    """The command to start a control loop at: (u0 (S,) [mm, ``model.servo_ids`` order], its tip error [m]):
    :func:`dacr_learn.solve_ik` of the saved ``model`` for the tip position ``target`` (3,) [m], warm-started at the
    ``current`` command (S,) [mm], the first successful of ``solutions`` (the nearest to ``current``), inside
    :meth:`.checkpoint.HardwareModel.servo_range`, within ``options.pos_tolerance`` (:class:`dacr_learn.ik.IKOptions`).
    ValueError when no solution reaches the target (naming the smallest miss) or for inputs of the wrong shape.
    """
    options = IKOptions() if options is None else options
    target = torch.as_tensor(target, dtype=F64)
    current = torch.as_tensor(current, dtype=F64)
    if target.shape != (3,) or current.shape != (len(model.servo_ids),):
        raise ValueError(f"target (3,) [m] and current ({len(model.servo_ids)},) [mm] expected, got "
                         f"{tuple(target.shape)} and {tuple(current.shape)}")
    lower, upper = model.servo_range()
    result = solve_ik(model, target[None], n_solutions=solutions, q0=current.clamp(lower, upper)[None],
                      position_only=True, options=options)
    if not bool(result.success[0, 0]):
        raise ValueError(f"target {[round(1e3 * v, 3) for v in target.tolist()]} mm: no command in the recorded "
                         f"servo range reaches it per the model (closest {1e3 * float(result.pos_err[0].min()):.3f} "
                         f"mm off, tolerance {1e3 * options.pos_tolerance:.4f} mm)")
    return result.q[0, 0], float(result.pos_err[0, 0])


def run_control(fk, jacobian, targets: Tensor, servo0: Tensor, state0: Tensor | None, lower: Tensor,
                upper: Tensor, config: ServoControl = ServoControl(), settle: int = 0,
                pull_sign: Tensor | None = None) -> dict[str, np.ndarray]:
    """Track ``targets`` (T, 3) [m] from command ``servo0`` (S,) [mm] and play state ``state0`` (1, m, 2) (None: a
    static model) with the exported ``fk`` / ``jacobian`` modules (or HardwareFK / HardwareJacobian). Each step the
    plant executes u → tip and the new state; J = ∂tip/∂u at the state before the step; u ← clip(u + DLS(J,
    gain·(p* − tip) + Δp*; slack servos pulled in, :func:`slack_pull`), lower, upper). ``pull_sign`` (S,): +1 where
    a larger command pulls the tendon in, −1 where a smaller one does (default +1). The first ``settle`` steps hold
    targets[0] and are not returned. Returns numpy arrays: desired, actual (T, 3) [m], servo (T, S) [mm], step_us
    (T,) (controller step: Jacobian + DLS + clip).
    """
    scale = ((upper - lower) / 2).to(F64).clamp_min(1e-9)
    lower, upper = lower.to(F64), upper.to(F64)
    u, state = servo0.to(F64).clamp(lower, upper), state0
    pull_sign = torch.ones_like(u) if pull_sign is None else pull_sign.to(F64)
    desired = torch.cat([targets[:1].expand(settle, 3), targets, targets[-1:]]).to(F64)
    rows: dict[str, list] = {"desired": [], "actual": [], "servo": [], "step_us": []}
    with torch.no_grad():
        for k in range(settle + len(targets)):
            before = state
            out = fk(u[None]) if state is None else fk(u[None], state)
            tip, state = out[0][0].to(F64), (None if state is None else out[2])
            t0 = time.perf_counter_ns()
            j = (jacobian(u[None]) if before is None else jacobian(u[None], before))[1][0]
            task = config.gain * (desired[k] - tip) + (desired[k + 1] - desired[k])
            pull = slack_pull(j, pull_sign, config.retension) if config.retension > 0 else None
            u_next = (u + scaled_dls_step(j, task, scale, config.damping, config.max_step, pull)).clamp(lower, upper)
            step_us = (time.perf_counter_ns() - t0) / 1e3
            if k >= settle:
                for key, v in (("desired", desired[k]), ("actual", tip), ("servo", u), ("step_us", step_us)):
                    rows[key].append(torch.as_tensor(v, dtype=F64))
            u = u_next
    return {k: torch.stack(v).numpy() for k, v in rows.items()}


def slack_pull(jac: Tensor, pull_sign: Tensor, retension: float) -> Tensor:
    """Scaled null-space step (S,) re-tensioning slack tendons: retension·pull_sign on the servos whose
    column of J (3, S) is zero (relative to the largest: a slack tendon), 0 elsewhere; pull_sign (S,) ±1."""
    column = torch.linalg.vector_norm(jac.to(F64), dim=-2)
    slack = column <= 1e-6 * column.max().clamp_min(1e-300)
    return torch.where(slack, retension * pull_sign.to(F64), torch.zeros_like(column))


def servo_signs(meta: dict) -> Tensor:
    """(S,) ±1 of an export's servo map in ``servo_ids`` order: the direction that pulls each tendon in."""
    sign = {str(a["servo"]): float(a["sign"]) for a in meta["servo_map"]["servos"]}
    return torch.tensor([sign[str(i)] for i in meta["servo_ids"]], dtype=F64)


def load_hardware_export(export: str | Path):
    """(fk, jacobian, initial_state or None, metadata) of a hardware export (``python -m dacr_learn.export
    --ckpt model.pt``); ValueError for an export of another task."""
    meta = dexport.read_metadata(export)
    if meta.get("task") != "hardware_fk":
        raise ValueError(f"{export}: expected a hardware model export (task 'hardware_fk'), got {meta.get('task')!r}")
    init = dexport.load(export, "initial_state") if meta["history"] else None
    return dexport.load(export, "fk"), dexport.load(export, "jacobian"), init, meta
