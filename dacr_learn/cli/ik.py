"""Solve IK for a file of targets: several verified solutions per target.

    python -m dacr_learn.ik (--robot ROBOT.yaml | --ckpt CKPT) --targets T.npy --out S.npz --solutions K \
        [--position-only]
    python -m dacr_learn.ik --robot ROBOT.yaml --arm ARM.urdf --arm-tip LINK --mount M.npy --targets T.npy ...

T.npy: float64 (B, 4, 4) tip poses [m] in the robot's base frame, or (B, 3) tip positions with --position-only.
S.npz: q (B, K, N), success, pos_err, rot_err, iterations, distinct (B, K) (+ clearance with --scene, sigma for a
hardware model): what each means and what --ckpt accepts, docs/ik.md "Interface"; --scene: docs/body.md; --arm, the
whole-body IK of the arm carrying the robot (targets in the arm's base frame, q (B, K, n_arm + N)): docs/arm.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..checks import F64, prefix_errors
from ..ik import IKOptions, IKResult, as_solver_model, check_targets, solve_ik
from ..ik.collision import add_scene_arguments, scene_options
from .loading import composite_from_files, describe, load_array, load_solver_model, out_path, save_npz


def main(argv: list[str] | None = None) -> IKResult:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.ik", description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--robot", help="robot YAML file: solve on its analytic constant-curvature model")
    src.add_argument("--ckpt", help="trained FK / IK run or checkpoint, learned sampler, or hardware model.pt")
    p.add_argument("--targets", required=True, help="(B, 4, 4) poses or (B, 3) positions [m], float64 .npy")
    p.add_argument("--out", required=True, help="the .npz file to write")
    p.add_argument("--solutions", type=int, default=8, help="solutions per target, K (default 8)")
    p.add_argument("--position-only", action="store_true", help="targets are tip positions (B, 3)")
    p.add_argument("--tolerance", type=float, nargs=2, default=(1e-6, 1e-5), metavar=("POS", "ROT"),
                   help="success tolerance: position [m] and rotation [rad] (default 1e-6 1e-5)")
    p.add_argument("--q0", help="warm start (N,) or (B, N) .npy: the solution nearest it comes first")
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts (default 0)")
    p.add_argument("--batch", type=int, default=2000, help="targets solved at once (default 2000)")
    p.add_argument("--rerun", metavar="FILE.rrd", help="also write a Rerun recording of the first --show targets' "
                   "solutions (ghost backbones, target frames; robot models with an orientation)")
    p.add_argument("--show", type=int, default=4, help="targets in the --rerun recording (default 4)")
    p.add_argument("--arm", help="URDF of an arm carrying the robot: whole-body IK (docs/arm.md)")
    p.add_argument("--arm-tip", help="with --arm: the link the robot is mounted on")
    p.add_argument("--mount", help="with --arm: float64 (4, 4) .npy, the tip link → robot base transform [m]")
    add_scene_arguments(p)
    args = p.parse_args(argv)
    scene = scene_options(args)
    if args.solutions < 1:
        raise ValueError(f"--solutions: expected >= 1, got {args.solutions}")
    if args.batch < 1:
        raise ValueError(f"--batch: expected >= 1, got {args.batch}")
    if args.arm is None and (args.arm_tip is not None or args.mount is not None):
        raise ValueError("--arm-tip and --mount go with --arm ARM.urdf (whole-body IK); --arm is missing")
    out = out_path(args.out)
    started = time.perf_counter()
    targets = prefix_errors(f"--targets {args.targets}", check_targets,
                            torch.from_numpy(load_array(args.targets, "--targets")), args.position_only)
    q0 = None if args.q0 is None else torch.from_numpy(load_array(args.q0, "--q0"))
    model, seeder, description = load_solver_model(args.robot, args.ckpt)
    options = IKOptions(pos_tolerance=args.tolerance[0], rot_tolerance=args.tolerance[1], seed=args.seed)
    solver_model = as_solver_model(model)
    if args.arm is not None:                                         # whole-body: arm + mount + this robot
        solver_model = composite_from_files(args.arm, args.arm_tip, args.mount, solver_model)
        seeder = solver_model.seeds
        description = f"{args.arm} ({args.arm_tip}) carrying the {description}; {describe(solver_model)}"
    parts = []
    chunks = range(0, targets.shape[0], args.batch)
    from tqdm import tqdm
    progress = tqdm(total=len(chunks), desc="IK", unit="batch", file=sys.stderr, disable=len(chunks) < 2)
    for start in chunks:
        t = targets[start:start + args.batch]
        q0_chunk = q0 if q0 is None or q0.dim() == 1 else q0[start:start + args.batch]
        seeds = None if seeder is None else seeder(t, args.solutions)
        parts.append(solve_ik(solver_model, t, args.solutions, q0=q0_chunk, position_only=args.position_only,
                              options=options, seeds=seeds, **scene))
        progress.update()
    progress.close()
    result = IKResult.concat(parts)
    arrays = {k: v for k, v in result.numpy().items()}
    arrays["q"] = arrays["q"].astype(np.float64)
    if hasattr(solver_model, "hardware"):                            # a hardware model: σ of each solution
        b, k, n = result.q.shape
        _, sigma = solver_model.hardware.predict(result.q.reshape(-1, n), static=True)
        arrays["sigma"] = sigma.reshape(b, k, 3).to(F64).numpy()
    save_npz(out, arrays)
    if args.rerun:
        _record(Path(args.rerun), solver_model, targets[:args.show], result.q[:args.show], result.success[:args.show],
                **scene)
    ok = result.success
    print(f"solved {int(ok.any(1).sum())}/{ok.shape[0]} targets ({int(ok.sum())}/{ok.numel()} solutions, "
          f"{result.distinct.sum(1).double().mean():.1f} distinct per target) on the {description} "
          f"in {time.perf_counter() - started:.1f} s → {out}")
    return result


def _record(path: Path, model, targets: torch.Tensor, q: torch.Tensor, success: torch.Tensor, scene=None,
            clearance: float = 0.0) -> None:
    """Rerun recording of a solve: target frames, solutions' backbones (:func:`dacr_learn.viz.ik.log_ik_solutions`)."""
    import rerun as rr

    from ..kinematics import backbone_points
    from ..layers import ClarkeEncoder
    from ..viz.ik import ik_blueprint, log_ik_solutions
    spec = getattr(model, "spec", None)
    if spec is None or targets.dim() != 3:
        raise ValueError("--rerun: needs a robot model (not a hardware model) and pose targets (B, 4, 4)")
    b, k, n = q.shape
    lines = backbone_points(spec, ClarkeEncoder(spec).to(F64)(q.reshape(-1, n))).view(b, k, -1, 3)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("dacr_learn_ik")
    rec.save(str(path), default_blueprint=ik_blueprint())
    if scene is None:
        log_ik_solutions(rec, "ik", targets, lines, success)
    else:                                        # obstacles, and the body coloured by clearance
        from ..body import body_layout
        from ..viz.obstacles import log_scene_solutions
        log_scene_solutions(rec, "ik", scene, targets, lines, body_layout(spec, 16)[1], success, clearance)
    rec.flush()
