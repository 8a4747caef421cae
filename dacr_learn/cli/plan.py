"""Plan a follow-the-leader insertion along a path (docs/plan.md).

    python -m dacr_learn.plan ftl (--robot R.yaml | --ckpt C) --arm ARM.urdf --arm-tip LINK --mount M.npy \
        --path P.npy --out PLAN.npz [--steps T] [--tolerance REL] [--scene S.yaml [--clearance D]] \
        [--rerun FILE.rrd]

P.npy: float64 (W, 3) [m] in the arm's base frame, a dense polyline (spacing ≤ 1 % of the robot's length): the
tip enters it at P[0] and follows it to P[-1]. Without --arm the robot's base is fixed and P is in its frame.

PLAN.npz: q (T, n_arm + N) float64 (the arm's joints in the chain's order, then the robot's joint vector, as the
IK command line writes them); s (T,) [m] the tip's arc length along the path, 0 … min(path length, robot
length); tip_err (T,) [m] the tip's distance to the path point at s; shape_dev, shape_dev_max (T,) [m] mean and
max distance of the inserted body (the last min(s, L) of the backbone, resampled by arc length) to the traversed
path P[0 … s]; success (bool): every tip within --tolerance·L, inside every limit (URDF and the robot file's),
consecutive steps continuous and, with --scene, every step's clearance ≥ D (docs/plan.md); clearance (T,) [m]
the body's (and the arm links') clearance to the scene's obstacles (+inf without --scene); reason (str): why
not, '' on success (also printed).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from ..checks import F64
from ..ik.collision import add_scene_arguments, scene_options
from ..plan import FTLOptions, FTLPlan, plan_ftl
from ..plan.path import Path as PolylinePath
from .loading import composite_from_files, describe, load_array, load_solver_model, out_path, save_npz


def load_path(path: str) -> PolylinePath:
    """--path P.npy: a float (W, 3) polyline [m]. ValueError naming the flag and what was wrong."""
    array = load_array(path, "--path")
    if not np.issubdtype(array.dtype, np.floating):
        raise ValueError(f"--path {path}: expected float64 (W, 3) points [m], got dtype {array.dtype}")
    try:
        return PolylinePath(torch.from_numpy(array.astype(np.float64)), f"--path {path}")
    except ValueError as err:
        raise ValueError(str(err)) from err


def write_plan(out: Path, plan: FTLPlan) -> None:
    """PLAN.npz, atomically (:func:`~.loading.save_npz`)."""
    save_npz(out, plan.arrays())


def build_model(args: argparse.Namespace):
    """The planner's model: --robot / --ckpt, inside the arm of --arm/--arm-tip/--mount when given."""
    from ..ik.adapters import as_solver_model
    model, _, description = load_solver_model(args.robot, args.ckpt)
    model = as_solver_model(model)
    if args.arm is None:
        if args.arm_tip is not None or args.mount is not None:
            raise ValueError("--arm-tip and --mount go with --arm ARM.urdf; --arm is missing")
        return model, description
    composite = composite_from_files(args.arm, args.arm_tip, args.mount, model)
    return composite, f"{args.arm} ({args.arm_tip}) carrying the {description}; {describe(composite)}"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.plan", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="method", required=True, metavar="METHOD")
    f = sub.add_parser("ftl", help="follow-the-leader insertion along a path",
                       description="Follow-the-leader insertion along a path (docs/plan.md).")
    src = f.add_mutually_exclusive_group(required=True)
    src.add_argument("--robot", help="robot YAML file: its analytic constant-curvature model")
    src.add_argument("--ckpt", help="a trained model with a body (run or checkpoint)")
    f.add_argument("--arm", help="URDF of the arm carrying the robot (configs/arms/free_base.urdf: an ideal "
                   "6-DoF base; insertion_stage.urdf: one prismatic joint)")
    f.add_argument("--arm-tip", help="with --arm: the link the robot is mounted on")
    f.add_argument("--mount", help="with --arm: float64 (4, 4) .npy, the tip link → robot base transform [m]")
    f.add_argument("--path", required=True, help="float64 (W, 3) .npy polyline [m] in the arm's base frame")
    f.add_argument("--out", required=True, help="the PLAN.npz file to write")
    f.add_argument("--steps", type=int, help="steps T, evenly spaced along the path (default: spacing ≤ 1 %% of "
                   "the robot's length; sub-steps the planner takes between them are not written)")
    f.add_argument("--tolerance", type=float, default=1e-6,
                   help="tip tolerance relative to the robot's length (default 1e-6)")
    add_scene_arguments(f)
    f.add_argument("--rerun", metavar="FILE.rrd", help="also write a Rerun recording of the insertion")
    return p


def main(argv: list[str] | None = None) -> FTLPlan:
    args = _parser().parse_args(argv)
    scene = scene_options(args)
    if args.steps is not None and args.steps < 2:
        raise ValueError(f"--steps: expected >= 2, got {args.steps}")
    if not (np.isfinite(args.tolerance) and args.tolerance > 0):
        raise ValueError(f"--tolerance: expected a relative tolerance > 0, got {args.tolerance}")
    out = out_path(args.out)
    started = time.perf_counter()
    path = load_path(args.path)
    model, description = build_model(args)
    plan = plan_ftl(model, path, args.steps, FTLOptions(tolerance=args.tolerance), **scene)
    write_plan(out, plan)
    if args.rerun:
        record(Path(args.rerun), model, path, plan)
    length = plan.length
    verdict = "success" if plan.success else f"FAILED: {plan.reason}"
    mean, worst = (100 * float(v) / length for v in (plan.shape_dev.mean(), plan.shape_dev_max.max()))
    print(f"{plan.s.shape[0]} steps along {path.length:.4g} m (s up to {float(plan.s[-1]):.4g} m) with the "
          f"{description}: tip error max {float(plan.tip_err.max()) / length:.2e} L, shape deviation mean "
          f"{mean:.3f} % / max {worst:.3f} % of L = {length:.4g} m"
          f"{f', clearance min {float(plan.clearance.min()):.3g} m' if scene else ''}; {verdict}; "
          f"{time.perf_counter() - started:.1f} s → {out}")
    return plan


def record(file: Path, model, path: PolylinePath, plan: FTLPlan) -> None:
    """The plan as a Rerun recording (:func:`dacr_learn.viz.plan.record_insertion`)."""
    from ..arm import Composite
    from ..plan.body import body
    from ..viz.plan import record_insertion
    x = plan.x
    pos, rot, _ = model.tip_and_jacobian(x)
    tips = torch.eye(4, dtype=F64).repeat(x.shape[0], 1, 1)
    tips[:, :3, 3] = pos
    if rot is not None:
        tips[:, :3, :3] = rot
    traversed = [torch.cat([path.points[path.arc < s], path.at(s[None])]).numpy() for s in plan.s]
    frames = bases = None
    if isinstance(model, Composite):
        theta = x[:, :model.num_arm]
        frames, bases = model.arm.frames(theta).numpy(), model.base_pose(theta).numpy()
    record_insertion(file, path.points.numpy(), traversed, body(model, x).points.numpy(), tips.numpy(),
                     plan.length, plan.shape_dev.numpy(), plan.shape_dev_max.numpy(), plan.tip_err.numpy(),
                     frames, bases)


def package_main(argv: list[str] | None = None) -> None:
    """The CLI without its return value (``run_cli`` exits with the status it returns)."""
    main(argv)
