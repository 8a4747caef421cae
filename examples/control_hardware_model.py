"""Resolved-rate control of an exported hardware model: servo commands [mm] → tip, run causally.

**The plant is the learned model itself.** The exported ``fk`` module of a saved hardware model
(e.g. FTDCR v4's default, a history model) plays the robot: each control step it executes the
command and returns the tip and its new play (history) state, which is passed on to the next
step. The controller (:mod:`dacr_learn.hardware.deploy.control`) takes damped least-squares steps in
servo space on the exported ``jacobian`` module, clipped to the box of commands seen in the training
recording; ``--retension`` pulls slack tendons in through J's null space (on FTDCR v4's default it reaches a
far static target that stalls 16 mm short without it, but it jolts the tip where a tendon goes taut
mid-circle: docs/export.md). So this checks the deployment
plumbing (exported modules, Jacobian, explicit causal state) and the controller on the model; it
says nothing about how well the real robot would track (that is bounded by the model's own error,
docs/hardware.md).

Two tasks: a circle of ``--radius`` mm around the model's rest tip (command 0), ``--laps`` laps of
``--period`` steps in the motion-capture xy plane ``--drop`` mm below the rest tip, and static targets
(the model's tips at a few training commands, reachable by construction), each held for ``--hold``
steps. The circle starts at the command the IK solver gives for its first point
(:func:`dacr_learn.solve_ik` on the saved model the export was made from, ``--ckpt``, position only: the
solution nearest the rest command, inside the recorded servo range); the static targets start at the rest
command, so that they test the controller's own approach. Printed: the initial command's error, tracking
RMS / max [mm] and the controller step's p50 latency [µs]; written: ``--out``/summary.json.

    .venv/bin/python -m dacr_learn.hardware --data data/ftdcr_v4 --robot configs/robots/ftdcr_v4_calibrated.yaml \\
        --out runs/ftdcr_v4 --seeds 0 --save runs/ftdcr_v4_model
    .venv/bin/python -m dacr_learn.export --ckpt runs/ftdcr_v4_model/model.pt --out runs/ftdcr_v4_model/export --no-aoti
    .venv/bin/python examples/control_hardware_model.py --export runs/ftdcr_v4_model/export
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn.checks import F64  # noqa: E402
from dacr_learn.console import run_cli  # noqa: E402
from dacr_learn.deploy import export as dexport  # noqa: E402
from dacr_learn.hardware.deploy.checkpoint import HardwareModel, load_hardware_model  # noqa: E402
from dacr_learn.hardware.deploy.control import (  # noqa: E402
    ServoControl,
    initial_command,
    load_hardware_export,
    run_control,
    servo_signs,
)
from dacr_learn.hardware.recording import load_recording  # noqa: E402


def training_commands(servo_ids: list[str], recording: Path) -> Tensor:
    """The commands (N, S) [mm] of a recording, columns in the model's ``servo_ids`` order."""
    rec = load_recording(recording, units="mm")
    where = {str(i): k for k, i in enumerate(rec.servo_ids)}
    missing = [i for i in servo_ids if str(i) not in where]
    if missing:
        raise ValueError(f"{recording}: lacks the servo columns {missing} of the model (has {list(rec.servo_ids)})")
    return 1e3 * rec.servo[:, [where[str(i)] for i in servo_ids]]


def source_model(export: str | Path, meta: dict, ckpt: str | Path | None = None) -> HardwareModel:
    """The saved hardware model an export was made from: ``ckpt``, else its metadata's ``source_checkpoint`` (as
    written, then next to the export), checked against the export's checksum and servo ids (FileNotFoundError,
    ValueError)."""
    export = Path(export)
    if ckpt is None:
        named = Path(meta["source_checkpoint"]["path"])
        found = [p for p in (named, export.parent / named.name) if p.is_file()]
        if not found:
            raise FileNotFoundError(f"{export}: the checkpoint it was exported from, {named}, is not there; "
                                    f"pass it (--ckpt model.pt)")
        ckpt = found[0]
    ckpt = Path(ckpt)
    digest = dexport.file_sha256(ckpt)
    if digest != meta["source_checkpoint"]["sha256"]:
        raise ValueError(f"{ckpt}: not the checkpoint {export} was exported from (sha256 {digest[:12]}…, the export "
                         f"names {meta['source_checkpoint']['path']}, {meta['source_checkpoint']['sha256'][:12]}…)")
    model = load_hardware_model(ckpt)
    if [str(i) for i in model.servo_ids] != [str(i) for i in meta["servo_ids"]]:
        raise ValueError(f"{ckpt}: servo ids {list(model.servo_ids)}, the export's are {meta['servo_ids']}")
    return model


def circle(center: Tensor, radius: float, drop: float, steps: int) -> Tensor:
    """(steps, 3) [m]: a circle of ``radius`` [m] in the xy plane, ``drop`` [m] below ``center``."""
    t = 2 * torch.pi * torch.arange(steps, dtype=F64) / steps
    return center.to(F64) + torch.stack([radius * torch.cos(t), radius * torch.sin(t), torch.full_like(t, -drop)], -1)


def static_targets(fk, jac, init, commands: Tensor, rest: Tensor, lower: Tensor, upper: Tensor,
                   config: ServoControl, hold: int, pull_sign: Tensor | None = None, count: int = 4) -> dict[str, dict]:
    """Reach the model's tips at ``count`` evenly spaced training ``commands`` (N, S) [mm] from the rest
    command, one by one (each target: the model's tip at that command, play state started there)."""
    out = {}
    for n, row in enumerate(torch.linspace(0, len(commands) - 1, count + 2)[1:-1].round().long().tolist()):
        goal = commands[row]
        state_goal = None if init is None else init(goal[None])
        target = fk(goal[None], *(() if init is None else (state_goal,)))[0][0].to(F64)
        state0 = None if init is None else init(rest[None])
        res = run_control(fk, jac, target.expand(hold, 3), rest, state0, lower, upper, config, pull_sign=pull_sign)
        err = np.linalg.norm(res["actual"] - res["desired"], axis=-1)
        out[f"static_{n}"] = {"train_row": row, "start_error_mm": 1e3 * float(err[0]),
                              "final_error_mm": 1e3 * float(err[-1]), "step_p50_us": float(np.median(res["step_us"]))}
    return out


def tracking_errors(result: dict[str, np.ndarray]) -> dict[str, float]:
    err = np.linalg.norm(result["actual"] - result["desired"], axis=-1)
    return {"rms_mm": 1e3 * float(np.sqrt(np.mean(err**2))), "median_mm": 1e3 * float(np.median(err)),
            "p95_mm": 1e3 * float(np.percentile(err, 95)), "max_mm": 1e3 * float(err.max()),
            "step_p50_us": float(np.median(result["step_us"])), "steps": int(err.size)}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--export", type=Path, default=ROOT / "runs" / "ftdcr_v4_model" / "export",
                   help="hardware model export (python -m dacr_learn.export --ckpt model.pt --out DIR)")
    p.add_argument("--ckpt", type=Path, default=None,
                   help="the saved model the export was made from, whose IK gives the initial command "
                        "(default: the checkpoint its metadata names)")
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
    if not (args.export / "metadata.json").is_file():
        raise FileNotFoundError(f"{args.export}: no hardware model export (metadata.json missing); "
                                "build one with the commands in this script's docstring")
    fk, jac, init, meta = load_hardware_export(args.export)
    model = source_model(args.export, meta, args.ckpt)
    commands = training_commands(meta["servo_ids"], args.train)
    lower, upper = commands.min(0).values, commands.max(0).values          # the box of the training commands
    config = ServoControl(gain=args.gain, retension=args.retension)
    pull_sign = servo_signs(meta)
    tip_of = lambda u: fk(u[None], *(() if init is None else (init(u[None]),)))[0][0].to(F64)  # noqa: E731
    rest = torch.zeros(len(meta["servo_ids"]), dtype=F64).clamp(lower, upper)
    path = circle(tip_of(rest), 1e-3 * args.radius, 1e-3 * args.drop, args.period).repeat(args.laps, 1)
    start, ik_error = initial_command(model, path[0], rest)                # the IK's command for the first point
    if not bool(((start >= lower) & (start <= upper)).all()):
        raise ValueError(f"--train {args.train}: its command box does not hold the model's recorded servo range "
                         f"(the IK's command {start.tolist()} mm lies outside it); pass the model's training recording")
    state0 = None if init is None else init(start[None])
    initial = {"servo_mm": start.tolist(), "ik_error_mm": 1e3 * ik_error,
               "export_error_mm": 1e3 * float((tip_of(start) - path[0]).norm()),
               "largest_change_from_rest_mm": float((start - rest).abs().max()),
               "from": "dacr_learn.solve_ik on the saved model, position only, the solution nearest the rest command"}
    results = {"circle": tracking_errors(run_control(fk, jac, path, start, state0, lower, upper, config, args.settle,
                                            pull_sign))}
    results.update(static_targets(fk, jac, init, commands, rest, lower, upper, config, args.hold, pull_sign))
    summary = {"export": str(args.export), "model": meta["model"], "robot": meta["robot"]["name"],
               "history": meta["history"], "plant": "the learned model itself (exported fk module)",
               "initial_command": initial,
               "servo_box_mm": {"lower": lower.tolist(), "upper": upper.tolist()}, "controller": asdict(config),
               "circle": {"radius_mm": args.radius, "drop_mm": args.drop, "period_steps": args.period,
                          "laps": args.laps, "settle_steps": args.settle}, "results": results}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, args.out)
    return summary


def print_summary(summary: dict, out: Path) -> None:
    print(f"\nresolved-rate control of the exported hardware model {summary['model']} ({summary['robot']}); "
          f"THE PLANT IS THE LEARNED MODEL ITSELF (its exported fk module, play state passed on each step), "
          f"so this checks the controller and the deployed modules, not the real robot")
    c, i = summary["results"]["circle"], summary["initial_command"]
    print(f"  initial command (IK of the saved model for the circle's first point, nearest the rest command): "
          f"{i['ik_error_mm']:.2e} mm from it per the model, {i['export_error_mm']:.2e} mm per the export, "
          f"servos up to {i['largest_change_from_rest_mm']:.2f} mm from rest")
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
