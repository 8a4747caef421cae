"""Resolved-rate control of an exported hardware model in servo space: servo commands [mm] → tip, run causally.

The controller linearises the exported ``jacobian`` module (J = ∂tip/∂servo [m/mm]) along the plant's last
step (the command from the play state before it: while the play is being dragged this is the sliding
derivative a continuing motion sees; evaluated at the state after the step, a dragged play sits exactly at
its width and the one-sided "reversal" derivative ∝ 1/play width is taken, which made the loop diverge on a
strongly history-dependent test model) and takes a damped least-squares step in servo space
(:func:`dacr_learn.deploy.control.scaled_dls_step`, servo displacements scaled by their half-range), clipped
to a box of commands (those of the training recording). A slack tendon's column of J is zero, so the tip task
alone never re-tensions it; opt-in, a second task in J's null space pulls each slack servo in
(``ServoControl.retension``, :func:`slack_pull`: docs/export.md for the trade-off).

- :func:`run_control`: track targets with a plant (``fk``, e.g. the exported model itself) and a Jacobian;
- :func:`static_targets`: reach the model's tips at a few training commands from the rest command;
- :func:`load_hardware_export`, :func:`training_commands`, :func:`servo_signs`, :func:`circle`,
  :func:`tracking_errors`: the pieces around them.

examples/control_hardware_model.py runs both tasks on an export and prints the tracking errors.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ...deploy import export as dexport
from ...deploy.control import scaled_dls_step
from ..recording import load_recording

__all__ = ["ServoControl", "circle", "load_hardware_export", "run_control", "servo_signs", "slack_pull",
           "static_targets", "tracking_errors", "training_commands"]

_F64 = torch.float64


@dataclass(frozen=True)
class ServoControl:
    """gain: fraction of the tip error corrected per step, in (0, 1]; damping: λ [m] of the DLS;
    max_step: largest scaled servo step ‖Δu / s‖ per control step (s: each servo's half-range);
    retension: scaled step ‖Δu / s‖ per control step by which each *slack* servo (a zero column of J) is
    pulled in, in [0, max_step] (0: off, the default). The tip task alone never moves a slack tendon's
    servo (its column of J is zero), so a target that needs the tendon taut again can stall. The pull is in
    J's null space, so it does not move the tip until the tendon goes taut (its column turns non-zero and
    the pull stops); the step that crosses the taut onset does move it (docs/export.md: a trade-off)."""

    gain: float = 0.5
    damping: float = 2e-3
    max_step: float = 0.05
    retension: float = 0.0

    def __post_init__(self):
        if not 0 < self.gain <= 1:
            raise ValueError(f"gain: expected a value in (0, 1], got {self.gain}")
        if not self.damping >= 0 or not self.max_step > 0:
            raise ValueError(f"damping ≥ 0 [m] and max_step > 0 expected, got {self.damping}, {self.max_step}")
        if not 0 <= self.retension <= self.max_step:
            raise ValueError(f"retension: expected a value in [0, max_step = {self.max_step}], got {self.retension}")


def training_commands(servo_ids: list[str], recording: Path) -> Tensor:
    """The commands (N, S) [mm] of a recording, columns in the model's ``servo_ids`` order."""
    rec = load_recording(recording, units="mm")
    where = {str(i): k for k, i in enumerate(rec.servo_ids)}
    missing = [i for i in servo_ids if str(i) not in where]
    if missing:
        raise ValueError(f"{recording}: lacks the servo columns {missing} of the model (has {list(rec.servo_ids)})")
    return 1e3 * rec.servo[:, [where[str(i)] for i in servo_ids]]


def run_control(fk, jacobian, targets: Tensor, servo0: Tensor, state0: Tensor | None, lower: Tensor,
                upper: Tensor, config: ServoControl = ServoControl(), settle: int = 0,
                pull_sign: Tensor | None = None) -> dict[str, np.ndarray]:
    """Track ``targets`` (T, 3) [m] from command ``servo0`` (S,) [mm] and play state ``state0`` (1, m, 2)
    (None: a static model). ``fk`` / ``jacobian``: the exported modules (or HardwareFK / HardwareJacobian).

    Each step: the plant (``fk``) executes the command u with the current state → tip and the new state;
    J = ∂tip/∂u at (u, the state before this step: the tangent of the plant's step, module docstring);
    u ← clip(u + DLS(J, gain·(p* − tip) + Δp*; slack servos pulled in, :func:`slack_pull`), lower, upper),
    ``pull_sign`` (S,): +1 where a larger command pulls the tendon in, −1 where a smaller one does (the servo
    map's signs; default all +1). The first
    ``settle`` steps hold targets[0] and are not returned. Returns numpy arrays of the tracking phase:
    desired, actual (T, 3) [m], servo (T, S) [mm], step_us (T,) (controller step: Jacobian + DLS + clip).
    """
    scale = ((upper - lower) / 2).to(_F64).clamp_min(1e-9)
    lower, upper = lower.to(_F64), upper.to(_F64)
    u, state = servo0.to(_F64).clamp(lower, upper), state0
    pull_sign = torch.ones_like(u) if pull_sign is None else pull_sign.to(_F64)
    desired = torch.cat([targets[:1].expand(settle, 3), targets, targets[-1:]]).to(_F64)
    rows: dict[str, list] = {"desired": [], "actual": [], "servo": [], "step_us": []}
    with torch.no_grad():
        for k in range(settle + len(targets)):
            before = state
            out = fk(u[None]) if state is None else fk(u[None], state)
            tip, state = out[0][0].to(_F64), (None if state is None else out[2])
            t0 = time.perf_counter_ns()
            j = (jacobian(u[None]) if before is None else jacobian(u[None], before))[1][0]
            task = config.gain * (desired[k] - tip) + (desired[k + 1] - desired[k])
            pull = slack_pull(j, pull_sign, config.retension) if config.retension > 0 else None
            u_next = (u + scaled_dls_step(j, task, scale, config.damping, config.max_step, pull)).clamp(lower, upper)
            step_us = (time.perf_counter_ns() - t0) / 1e3
            if k >= settle:
                for key, v in (("desired", desired[k]), ("actual", tip), ("servo", u), ("step_us", step_us)):
                    rows[key].append(torch.as_tensor(v, dtype=_F64))
            u = u_next
    return {k: torch.stack(v).numpy() for k, v in rows.items()}


def slack_pull(jac: Tensor, pull_sign: Tensor, retension: float) -> Tensor:
    """Scaled null-space step (S,) re-tensioning slack tendons: retension·pull_sign on the servos whose
    column of J (3, S) is zero (relative to the largest: a slack tendon), 0 elsewhere; pull_sign (S,) ±1."""
    column = torch.linalg.vector_norm(jac.to(_F64), dim=-2)
    slack = column <= 1e-6 * column.max().clamp_min(1e-300)
    return torch.where(slack, retension * pull_sign.to(_F64), torch.zeros_like(column))


def servo_signs(meta: dict) -> Tensor:
    """(S,) ±1 of an export's servo map in ``servo_ids`` order: the direction that pulls each tendon in."""
    sign = {str(a["servo"]): float(a["sign"]) for a in meta["servo_map"]["servos"]}
    return torch.tensor([sign[str(i)] for i in meta["servo_ids"]], dtype=_F64)


def circle(center: Tensor, radius: float, drop: float, steps: int) -> Tensor:
    """(steps, 3) [m]: a circle of ``radius`` [m] in the xy plane, ``drop`` [m] below ``center``."""
    t = 2 * torch.pi * torch.arange(steps, dtype=_F64) / steps
    return center.to(_F64) + torch.stack([radius * torch.cos(t), radius * torch.sin(t), torch.full_like(t, -drop)], -1)


def tracking_errors(result: dict[str, np.ndarray]) -> dict[str, float]:
    err = np.linalg.norm(result["actual"] - result["desired"], axis=-1)
    return {"rms_mm": 1e3 * float(np.sqrt(np.mean(err**2))), "median_mm": 1e3 * float(np.median(err)),
            "p95_mm": 1e3 * float(np.percentile(err, 95)), "max_mm": 1e3 * float(err.max()),
            "step_p50_us": float(np.median(result["step_us"])), "steps": int(err.size)}


def load_hardware_export(export: str | Path):
    """(fk, jacobian, initial_state or None, metadata) of a hardware export (``python -m dacr_learn.export
    --ckpt model.pt``); ValueError for an export of another task."""
    meta = dexport.read_metadata(export)
    if meta.get("task") != "hardware_fk":
        raise ValueError(f"{export}: expected a hardware model export (task 'hardware_fk'), got {meta.get('task')!r}")
    init = dexport.load(export, "initial_state") if meta["history"] else None
    return dexport.load(export, "fk"), dexport.load(export, "jacobian"), init, meta


def static_targets(fk, jac, init, commands: Tensor, rest: Tensor, lower: Tensor, upper: Tensor,
                   config: ServoControl, hold: int, pull_sign: Tensor | None = None, count: int = 4) -> dict[str, dict]:
    """Reach the model's tips at ``count`` evenly spaced training ``commands`` (N, S) [mm] from the rest
    command, one by one (each target: the model's tip at that command, play state started there)."""
    out = {}
    for n, row in enumerate(torch.linspace(0, len(commands) - 1, count + 2)[1:-1].round().long().tolist()):
        goal = commands[row]
        state_goal = None if init is None else init(goal[None])
        target = fk(goal[None], *(() if init is None else (state_goal,)))[0][0].to(_F64)
        state0 = None if init is None else init(rest[None])
        res = run_control(fk, jac, target.expand(hold, 3), rest, state0, lower, upper, config, pull_sign=pull_sign)
        err = np.linalg.norm(res["actual"] - res["desired"], axis=-1)
        out[f"static_{n}"] = {"train_row": row, "start_error_mm": 1e3 * float(err[0]),
                              "final_error_mm": 1e3 * float(err[-1]), "step_p50_us": float(np.median(res["step_us"]))}
    return out
