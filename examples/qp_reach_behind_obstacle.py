"""Reach behind an obstacle: constrained (QP) control side by side with today's resolved-rate controllers.

Two scenes (scene files in configs/scenes/, loaded with :func:`dacr_learn.scene.load_scene`), each from the same
start along the same target path, with the same gains and every limit:

- ``robot`` (configs/scenes/reach_tdcr3.yaml): the 3-segment TDCR (configs/robots/tdcr_3seg_coupled.yaml) on a
  fixed base; a sphere stands beside its upper half and the tip target moves from the straight tip to a point
  behind the sphere. Compared: :class:`dacr_learn.deploy.control.ResolvedRateController` (damped least squares,
  limits by saturation) and :class:`dacr_learn.deploy.qp_control.QPController` (one QP per step: limits, joint
  speeds, clearance dampers).
- ``arm`` (configs/scenes/reach_panda_port.yaml): the Panda holds the robot through a 5 mm port just above a wall
  with a 50 mm opening (as in examples/track_port.py); the tip tracks a circle behind the port while a sphere sits
  inside the cone the body sweeps. Compared: :class:`~dacr_learn.arm.control.WholeBodyController`,
  :class:`~dacr_learn.arm.control.DecoupledController` and :class:`~dacr_learn.arm.qp_control.WholeBodyQPController`,
  all with the Panda's URDF velocity limits at ``--dt`` (10 ms).

The QP controllers take the scene (``scene=``): their dampers act on the clearances of the robot's body
(``--points`` per segment) to every obstacle, with the scene's closed-form distance gradients times the body's
analytic Jacobian (:mod:`dacr_learn.deploy.qp_clearance`). Printed per controller (and in ``summary.json``;
the joint paths in ``paths.npz``): collision steps and the minimum clearance [mm] (a dense check: 64 points
per segment), the tip position error (RMS, max) [mm] over the path and at its end, steps with a variable at a
limit, limit violations of the commanded joints (the model's own check from the joints), the port's worst
excursion (arm scene) and the median step time [µs] (eager, batch 1). ``--rerun FILE`` writes a recording: per
controller (side by side in y) the obstacles, the target and tracked tip paths, and the body coloured by its
clearance (red: penetrating, orange: closer than the dampers' safety distance, green: clear).

    .venv/bin/python examples/qp_reach_behind_obstacle.py                 # both scenes, ~1-2 min on a laptop CPU
    .venv/bin/python examples/qp_reach_behind_obstacle.py --scene robot --rerun runs/qp_reach/qp_reach.rrd
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn.arm.control import DecoupledController, Port, WholeBodyConfig, WholeBodyController  # noqa: E402
from dacr_learn.arm.qp_control import WholeBodyQPController  # noqa: E402
from dacr_learn.cli.loading import composite_from_files  # noqa: E402
from dacr_learn.deploy.control import ControllerConfig, ResolvedRateController  # noqa: E402
from dacr_learn.deploy.qp_control import QPConfig, QPController  # noqa: E402
from dacr_learn.ik import ConstantCurvature  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402
from dacr_learn.scene import Scene, load_scene  # noqa: E402

F64 = torch.float64
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
PANDA_READY = (0.0, -0.3, 0.0, -2.2, 0.0, 2.0, math.pi / 4)
SPACING = 0.35         # [m] in y between the controllers in the recording
SCENE_OFFSET = {"robot": -0.6, "arm": 0.0}    # [m] in x: the robot-alone scene beside the arm's
TIMELINE = "step"
SCENES = {"robot": ROOT / "configs" / "scenes" / "reach_tdcr3.yaml",
          "arm": ROOT / "configs" / "scenes" / "reach_panda_port.yaml"}


def cc_jacobian(model: ConstantCurvature) -> Callable:
    """The closed-form CC Jacobian as :class:`ResolvedRateController` takes it: q (B, N) → (pose, J_f, None)."""
    def jacobian(q: torch.Tensor):
        position, rotation, jac = model.tip_and_jacobian(model.variables(q))
        pose = torch.eye(4, dtype=F64).repeat(len(q), 1, 1)
        pose[:, :3, :3], pose[:, :3, 3] = rotation, position
        return pose, jac, None
    return jacobian


def body_clearance(model, scene: Scene, x: torch.Tensor, per_segment: int = 64) -> torch.Tensor:
    """The smallest clearance (B,) [m] of the model's body at x (B, D), ``per_segment`` points per segment (balls
    of the envelope radius), to the scene's obstacles."""
    body = model.body(x, per_segment)
    return (scene.distances(body.points)[0] - body.radius[:, None]).flatten(1).amin(-1)


def at_limit(limits, x: torch.Tensor, margin: float = 1e-6) -> torch.Tensor:
    """(B,) True where some variable lies within ``margin`` of its scale of a bound (a box face, a disk rim)."""
    tol = margin * limits.scale
    hit = ((x <= limits.lower + tol) | (x >= limits.upper - tol)).any(-1)
    if limits.disks.numel():
        hit |= (torch.linalg.vector_norm(x[:, limits.disks], dim=-1) >= limits.radius * (1 - margin)).any(-1)
    return hit


def run(model, controller, q0: torch.Tensor, path: torch.Tensor, scene: Scene, port: Port | None = None
        ) -> tuple[dict, np.ndarray]:
    """Track ``path`` (S, 3) or (S, 4, 4) from q0 (N,); the state at step i is measured against target i, then
    commanded towards it with the feedforward to target i + 1. Metrics of the whole run and the joints (S, N)."""
    pos_path = path if path.dim() == 2 else path[:, :3, 3]
    nxt = torch.cat([pos_path[1:], pos_path[-1:]])
    q, rows = q0[None].clone(), {k: [] for k in ("error", "clearance", "at_limit", "inside", "port", "time", "q")}
    for i in range(len(path)):
        c = model.check(q)
        x = model.variables(q)
        rows["q"].append(q[0].numpy())
        rows["error"].append(float((c.position[0] - pos_path[i]).norm()))
        rows["clearance"].append(float(body_clearance(model, scene, x)[0]))
        rows["at_limit"].append(bool(at_limit(model.limits, x)[0]))
        rows["inside"].append(bool(c.inside[0]) and float(c.constraint[0]) <= 1e-9)
        if port is not None:
            base = model.base_pose(x[:, :model.num_arm])[0, :3, 3]
            rows["port"].append(float((base - torch.tensor(port.centre, dtype=F64)).norm()))
        ff = (nxt[i] - pos_path[i])[None]
        t = time.perf_counter()
        q = controller.step(q, pos_path[i:i + 1], ff)
        rows["time"].append(time.perf_counter() - t)
    err, clear = 1e3 * np.array(rows["error"]), 1e3 * np.array(rows["clearance"])
    out = {"collisions": int((clear < 0).sum()), "min_clearance_mm": float(clear.min()),
           "error_rms_mm": float(np.sqrt(np.mean(err**2))), "error_max_mm": float(err.max()),
           "final_error_mm": float(err[-1]), "steps_at_a_limit": int(np.sum(rows["at_limit"])),
           "limit_violations": int(len(err) - np.sum(rows["inside"])), "steps": len(err),
           "step_p50_us": float(1e6 * np.median(rows["time"]))}
    if port is not None:
        out["port_max_mm"] = float(1e3 * max(rows["port"]))
    return out, np.stack(rows["q"])


def ramp(start: torch.Tensor, goal: torch.Tensor, move: int, hold: int) -> torch.Tensor:
    """(move + hold, 3): a smooth (cosine) move from start to goal, then ``hold`` steps at the goal."""
    s = 0.5 - 0.5 * torch.cos(math.pi * torch.arange(1, move + 1, dtype=F64) / move)
    return torch.cat([start + s[:, None] * (goal - start), goal.expand(hold, 3)])


def robot_setup(args) -> dict:
    """The robot alone (configs/scenes/reach_tdcr3.yaml): the model, the controllers, the start q0 (N,), the target
    path (S, 3) and the scene."""
    spec = RobotSpec.coerce(args.robot)
    model = ConstantCurvature(spec)
    length = spec.total_length
    scene = load_scene(SCENES["robot"])
    goal = torch.tensor([0.65 * length, 0.05 * length, 0.55 * length], dtype=F64)
    path = ramp(model.tip_and_jacobian(model.rest[None])[0][0], goal, args.steps, args.hold)
    controllers = {"resolved_rate": ResolvedRateController(spec, cc_jacobian(model), ControllerConfig(
                       gain=args.gain, damping=QPConfig().damping, max_step=args.max_step)),
                   "qp": QPController(model, qp_config(args), scene=scene, points_per_segment=args.points)}
    return {"model": model, "controllers": controllers, "q0": model.joints(model.rest[None])[0], "path": path,
            "scene": scene}


def arm_setup(args) -> dict:
    """The Panda through a port (configs/scenes/reach_panda_port.yaml); the tip circles behind it (as
    :func:`robot_setup`, and the port)."""
    model = composite_from_files(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8",
                                 ROOT / "configs" / "arms" / "panda_mount.npy", args.robot)
    n = model.num_arm
    ready = model.limits.project(torch.cat([torch.tensor(PANDA_READY, dtype=F64), model.robot.rest]))[:n]
    x0 = torch.cat([ready, model.robot.rest])
    base = model.base_pose(ready[None])[0]
    port = Port(tuple(base[:3, 3].tolist()), 0.005)
    t = 2 * math.pi * torch.arange(args.steps, dtype=F64) / args.steps
    ex, ey, ez = base[:3, 0], base[:3, 1], base[:3, 2]
    circle = base[:3, 3] + 0.22 * ez + 0.06 * (torch.cos(t)[:, None] * ex + torch.sin(t)[:, None] * ey)
    path = torch.cat([ramp(model.tip_and_jacobian(x0[None])[0][0], circle[0], args.hold, 0), circle])
    scene = load_scene(SCENES["arm"])
    wb = WholeBodyConfig(gain=args.gain, max_step=args.max_step, dt=args.dt)
    controllers = {"whole_body": WholeBodyController(model, wb, port),
                   "decoupled": DecoupledController(model, wb, port),
                   "whole_body_qp": WholeBodyQPController(model, qp_config(args), port, dt=args.dt, scene=scene,
                                                          points_per_segment=args.points)}
    return {"model": model, "controllers": controllers, "q0": model.joints(x0[None])[0], "path": path,
            "scene": scene, "port": port}


def qp_config(args) -> QPConfig:
    return QPConfig(gain=args.gain, max_step=args.max_step, safety=args.safety, influence=args.influence,
                    damper_gain=args.damper_gain, joint_step=args.joint_step)


def run_scene(setup: dict) -> tuple[dict, dict[str, np.ndarray]]:
    """Every controller of a setup over its path (:func:`run`): the summary and each controller's joints (S, N)."""
    port, results, paths = setup.get("port"), {}, {}
    for k, c in setup["controllers"].items():
        results[k], paths[k] = run(setup["model"], c, setup["q0"], setup["path"], setup["scene"], port)
    return ({"obstacles": list(setup["scene"].labels), **({"port_radius_mm": 1e3 * port.radius} if port else {}),
             "results": results}, paths)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", choices=("robot", "arm", "both"), default="both")
    p.add_argument("--robot", default=str(ROBOT))
    p.add_argument("--steps", type=int, default=200, help="steps of the move (robot) / of the circle (arm)")
    p.add_argument("--hold", type=int, default=100, help="steps holding the goal (robot) / reaching the circle (arm)")
    p.add_argument("--gain", type=float, default=0.5)
    p.add_argument("--max-step", type=float, default=0.05, help="largest scaled step per variable")
    p.add_argument("--joint-step", type=float, default=1e-3, help="largest joint step [m] (QP only)")
    p.add_argument("--safety", type=float, default=0.002, help="d_s [m]")
    p.add_argument("--influence", type=float, default=0.02, help="d_i [m]")
    p.add_argument("--damper-gain", type=float, default=0.002, help="ξ [m per step]")
    p.add_argument("--points", type=int, default=8, help="body points per segment the QP sees")
    p.add_argument("--dt", type=float, default=0.01, help="control period [s] for the arm's URDF velocity limits")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "qp_reach")
    p.add_argument("--rerun", type=Path, default=None, help="write a Rerun recording (.rrd) of the runs")
    p.add_argument("--every", type=int, default=5, help="steps between the bodies drawn in the recording")
    return p.parse_args(argv)


def print_table(name: str, scene: dict) -> None:
    print(f"\n{name}: {len(scene['obstacles'])} obstacles")
    cols = [("collisions", "collisions", "d"), ("min_clearance_mm", "min clear mm", ".2f"),
            ("error_rms_mm", "err RMS mm", ".2f"), ("error_max_mm", "err max mm", ".2f"),
            ("final_error_mm", "err end mm", ".2f"), ("steps_at_a_limit", "at limit", "d"),
            ("limit_violations", "violations", "d"), ("port_max_mm", "port max mm", ".3f"),
            ("step_p50_us", "step p50 µs", ".0f")]
    cols = [c for c in cols if c[0] in next(iter(scene["results"].values()))]
    print("  " + f"{'controller':>14}" + "".join(f"{h:>14}" for _, h, _ in cols))
    for ctrl, r in scene["results"].items():
        print("  " + f"{ctrl:>14}" + "".join(f"{r[k]:>14{f}}" for k, _, f in cols))


def write_recording(file: Path, setups: dict, paths: dict, args) -> None:
    """The Rerun recording of the module docstring: per scene and controller (side by side in y, ``SPACING``
    apart) the obstacles, the target path, the tracked tip path and every ``args.every`` steps the body coloured
    by its clearance (and the arm, in the arm scene)."""
    import rerun as rr
    import rerun.blueprint as rrb

    from dacr_learn.viz.arm import log_arm
    from dacr_learn.viz.layout import time_panel_at_end
    from dacr_learn.viz.obstacles import log_body_clearance, log_obstacles
    from dacr_learn.viz.scene import log_path
    file.parent.mkdir(parents=True, exist_ok=True)
    views = [rrb.Spatial3DView(origin=f"world/{name}", name=f"{name}: " + ", ".join(paths[name]))
             for name in setups]
    rec = rr.RecordingStream("dacr_qp_reach")
    rec.set_sinks(rr.FileSink(str(file)), default_blueprint=rrb.Blueprint(
        rrb.Horizontal(*views), time_panel_at_end(TIMELINE), collapse_panels=True))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for name, setup in setups.items():
        model, scene, path = setup["model"], setup["scene"], setup["path"]
        for j, (ctrl, q) in enumerate(paths[name].items()):
            root = f"world/{name}/{ctrl}"
            rec.set_time(TIMELINE, sequence=0)                    # obstacles and target from the first step on
            rec.log(root, rr.Transform3D(translation=[SCENE_OFFSET[name], SPACING * j, 0.0]), static=True)
            rec.log(f"{root}/label", rr.Points3D([path[0].numpy() + [0.0, 0.0, 0.05]], labels=[ctrl],
                                                 show_labels=True, radii=0.001), static=True)
            log_obstacles(rec, f"{root}/obstacles", scene)
            log_path(rec, f"{root}/target_path", path.numpy(), color=(60, 90, 220), radius=0.0012)
            x = model.variables(torch.from_numpy(q))
            tips = model.check(torch.from_numpy(q)).position.numpy()
            body = model.body(x, 16)
            for k in range(0, len(q), args.every):
                rec.set_time(TIMELINE, sequence=k)
                log_path(rec, f"{root}/tracked_path", tips[:k + 1], color=(230, 120, 20), radius=0.0008)
                log_body_clearance(rec, f"{root}/body", scene, body.points[k], body.radius, args.safety)
                if name == "arm":
                    log_arm(rec, f"{root}/arm", model.arm.frames(x[k:k + 1, :model.num_arm])[0], radius=0.015,
                            mount=model.base_pose(x[k:k + 1, :model.num_arm])[0])
    rec.disconnect()


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(1)
    summary, setups, paths = {"config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()
                                         if k != "out"}}, {}, {}
    for name, setup in (("robot", robot_setup), ("arm", arm_setup)):
        if args.scene in (name, "both"):
            setups[name] = setup(args)
            summary[name], paths[name] = run_scene(setups[name])
            print_table(name, summary[name])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    np.savez(args.out / "paths.npz", **{f"{s}/{c}": q for s, runs in paths.items() for c, q in runs.items()})
    if args.rerun is not None:
        write_recording(args.rerun, setups, paths, args)
        print(f"recording: {args.rerun}")
    return summary


if __name__ == "__main__":
    main()
