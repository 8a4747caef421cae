"""``python -m dacr_learn.arm.exported``: export the whole-body control step of an arm carrying a continuum robot
(:func:`dacr_learn.arm.exported.export_control_step`) and print its deviation from the eager controller.

    python -m dacr_learn.arm.exported --arm ARM.urdf --arm-tip LINK --mount M.npy --robot ROBOT.yaml --out DIR \\
        [--port X Y Z --port-radius R] [--gain G --damping L --max-step S --dt DT] [--no-aoti]
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..arm import exported
from ..arm.control import Port, WholeBodyConfig
from .loading import composite_from_files


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.arm.exported",
                                description=exported.__doc__.split("\n\n")[0])
    p.add_argument("--arm", required=True, help="the arm's URDF file")
    p.add_argument("--arm-tip", required=True, help="the link the robot is mounted on")
    p.add_argument("--mount", required=True, help="float64 (4, 4) .npy, the tip link → robot base transform [m]")
    p.add_argument("--robot", required=True, help="robot YAML file")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--port", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="keep the robot's base at this point [m] (arm base frame; default: no port)")
    p.add_argument("--port-radius", type=float, default=0.005, help="the port's radius [m] (default 0.005)")
    p.add_argument("--gain", type=float, default=0.5, help="fraction of the task error corrected per step")
    p.add_argument("--damping", type=float, default=1e-3, help="λ of the damped least squares [m]")
    p.add_argument("--max-step", type=float, default=0.05, help="largest scaled step per control step")
    p.add_argument("--dt", type=float, help="control period [s]: the arm's URDF velocity limits (default: off)")
    p.add_argument("--no-aoti", action="store_true", help="skip the AOTInductor package (minutes)")
    args = p.parse_args(argv)
    model = composite_from_files(args.arm, args.arm_tip, args.mount, args.robot)
    config = WholeBodyConfig(gain=args.gain, damping=args.damping, max_step=args.max_step, dt=args.dt)
    port = None if args.port is None else Port(tuple(args.port), args.port_radius)
    meta = exported.export_control_step(model, args.out, config=config, port=port, aoti=not args.no_aoti,
                                        sources={"arm": args.arm, "mount": args.mount, "robot": args.robot})
    for name, dev in meta["max_abs_deviation"].items():
        print(f"{Path(args.out) / name}: max deviation from the eager controller {dev:.2e}")
    return meta
