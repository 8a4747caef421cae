"""Resolved-rate control of an exported hardware model: servo commands [mm] → tip, run causally.

**The plant is the learned model itself.** The exported ``fk`` module of a saved hardware model
(e.g. FTDCR v4's default, a history model) plays the robot: each control step it executes the
command and returns the tip and its new play (history) state, which is passed on to the next
step. The controller linearises the exported ``jacobian`` module (J = ∂tip/∂servo [m/mm]) along the
plant's last step (the command from the state before it: while the play is being dragged this is the
sliding derivative a continuing motion sees; evaluated at the state after the step, a dragged play
sits exactly at its width and the one-sided "reversal" derivative ∝ 1/play width is taken, which
made the loop diverge on a strongly history-dependent test model) and takes a damped least-squares step in servo space
(:func:`dacr_learn.control.scaled_dls_step`, servo displacements scaled by their half-range),
clipped to the box of commands seen in the training recording. A slack tendon's column of J is zero,
so the tip task alone never re-tensions it; opt-in, a second task in J's null space pulls each slack
servo in (``--retension``, :func:`slack_pull`; on FTDCR v4's default it reaches a far static target
that stalls 16 mm short without it, but it jolts the tip where a tendon goes taut mid-circle:
docs/export.md). So this checks the deployment
plumbing (exported modules, Jacobian, explicit causal state) and the controller on the model; it
says nothing about how well the real robot would track (that is bounded by the model's own error,
docs/hardware.md).

Two tasks: a circle of ``--radius`` mm around the model's rest tip (command 0), ``--laps`` laps of
``--period`` steps in the motion-capture xy plane ``--drop`` mm below the rest tip, and static targets
(the model's tips at a few training commands, reachable by construction), each held for ``--hold``
steps. Printed: tracking RMS / max [mm] and the controller step's p50 latency [µs]; written:
``--out``/summary.json.

    .venv/bin/python -m dacr_learn.hardware --data data/ftdcr_v4 --robot configs/robots/ftdcr_v4_calibrated.yaml \\
        --out runs/ftdcr_v4 --seeds 0 --save runs/ftdcr_v4_model
    .venv/bin/python -m dacr_learn.export --ckpt runs/ftdcr_v4_model/model.pt --out runs/ftdcr_v4_model/export --no-aoti
    .venv/bin/python examples/control_hardware_model.py --export runs/ftdcr_v4_model/export
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn import export as dexport  # noqa: E402
from dacr_learn.console import run_cli  # noqa: E402
from dacr_learn.control import scaled_dls_step  # noqa: E402
from dacr_learn.hardware.recording import load_recording  # noqa: E402

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


def errors(result: dict[str, np.ndarray]) -> dict[str, float]:
    err = np.linalg.norm(result["actual"] - result["desired"], axis=-1)
    return {"rms_mm": 1e3 * float(np.sqrt(np.mean(err**2))), "median_mm": 1e3 * float(np.median(err)),
            "p95_mm": 1e3 * float(np.percentile(err, 95)), "max_mm": 1e3 * float(err.max()),
            "step_p50_us": float(np.median(result["step_us"])), "steps": int(err.size)}


def load_modules(export: Path):
    """(fk, jacobian, initial_state or None, metadata) of a hardware export."""
    meta = dexport.read_metadata(export)
    if meta.get("task") != "hardware_fk":
        raise ValueError(f"{export}: expected a hardware model export (task 'hardware_fk'), got {meta.get('task')!r}")
    init = dexport.load(export, "initial_state") if meta["history"] else None
    return dexport.load(export, "fk"), dexport.load(export, "jacobian"), init, meta


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--export", type=Path, default=ROOT / "runs" / "ftdcr_v4_model" / "export",
                   help="hardware model export (python -m dacr_learn.export --ckpt model.pt --out DIR)")
    p.add_argument("--train", type=Path, default=ROOT / "data" / "ftdcr_v4" / "train.csv",
                   help="training recording whose command range bounds the servos")
    p.add_argument("--radius", type=float, default=10.0, help="circle radius [mm]")
    p.add_argument("--drop", type=float, default=1.0, help="circle plane below the rest tip [mm]")
    p.add_argument("--period", type=int, default=400, help="control steps per lap")
    p.add_argument("--laps", type=int, default=2)
    p.add_argument("--settle", type=int, default=100, help="steps on the first target before tracking")
    p.add_argument("--hold", type=int, default=200, help="steps per static target")
    p.add_argument("--gain", type=float, default=0.5)
    p.add_argument("--retension", type=float, default=ServoControl.retension,
                   help="scaled step per control step pulling each slack tendon's servo in (null space; 0: off)")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "control_hardware")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if not (args.export / dexport.METADATA_FILE).is_file():
        raise FileNotFoundError(f"{args.export}: no hardware model export ({dexport.METADATA_FILE} missing); "
                                "build one with the commands in this script's docstring")
    fk, jac, init, meta = load_modules(args.export)
    commands = training_commands(meta["servo_ids"], args.train)
    lower, upper = commands.min(0).values, commands.max(0).values          # the box of the training commands
    config = ServoControl(gain=args.gain, retension=args.retension)
    pull_sign = servo_signs(meta)
    rest = torch.zeros(len(meta["servo_ids"]), dtype=_F64).clamp(lower, upper)
    state0 = None if init is None else init(rest[None])
    rest_tip = fk(rest[None], *(() if init is None else (state0,)))[0][0]
    path = circle(rest_tip, 1e-3 * args.radius, 1e-3 * args.drop, args.period).repeat(args.laps, 1)
    results = {"circle": errors(run_control(fk, jac, path, rest, state0, lower, upper, config, args.settle,
                                            pull_sign))}
    results.update(static_targets(fk, jac, init, commands, rest, lower, upper, config, args.hold, pull_sign))
    summary = {"export": str(args.export), "model": meta["model"], "robot": meta["robot"]["name"],
               "history": meta["history"], "plant": "the learned model itself (exported fk module)",
               "servo_box_mm": {"lower": lower.tolist(), "upper": upper.tolist()}, "controller": asdict(config),
               "circle": {"radius_mm": args.radius, "drop_mm": args.drop, "period_steps": args.period,
                          "laps": args.laps, "settle_steps": args.settle}, "results": results}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, args.out)
    return summary


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


def print_summary(summary: dict, out: Path) -> None:
    print(f"\nresolved-rate control of the exported hardware model {summary['model']} ({summary['robot']}); "
          f"THE PLANT IS THE LEARNED MODEL ITSELF (its exported fk module, play state passed on each step), "
          f"so this checks the controller and the deployed modules, not the real robot")
    c = summary["results"]["circle"]
    print(f"  circle r = {summary['circle']['radius_mm']:.0f} mm, {summary['circle']['laps']} laps of "
          f"{summary['circle']['period_steps']} steps: RMS {c['rms_mm']:.3f} mm, median {c['median_mm']:.4f} mm, "
          f"p95 {c['p95_mm']:.3f} mm, max {c['max_mm']:.3f} mm, "
          f"controller step p50 {c['step_p50_us']:.0f} µs")
    for name, r in summary["results"].items():
        if name.startswith("static"):
            print(f"  {name} (model tip at train row {r['train_row']}): {r['start_error_mm']:.2f} mm → "
                  f"{r['final_error_mm']:.4f} mm after the hold, step p50 {r['step_p50_us']:.0f} µs")
    print(f"  summary: {out / 'summary.json'}")


if __name__ == "__main__":
    sys.exit(run_cli(main))
