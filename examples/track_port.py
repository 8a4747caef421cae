"""Whole-body vs decoupled control of an arm carrying a continuum robot through a narrow port.

A Panda (configs/arms/panda.urdf) carries the 3-segment coupled TDCR (configs/robots/tdcr_3seg_coupled.yaml) on
a 100 mm spacer (configs/arms/panda_mount.npy). The robot's base — the tool point of the flange — must stay in a
port, a ball of ``--port-radius`` (5 mm) around where it starts: a remote centre of motion, as in keyhole
surgery or inspection through a hole. The tip tracks a pose path behind the port: a circle of ``--circle``
(80 mm) radius at ``--depth`` (220 mm) along the port axis, the tip tilted ``--tilt`` (0.7 rad) outwards.
Two schemes run the same path from the same start, with the same gains and every limit (URDF joint
boxes, bend disks, length ranges; :mod:`dacr_learn.arm.control`):

- whole body: one resolved-rate step of all 16 variables, the port as rows of the task;
- decoupled: the arm first (its resolved-rate step for the target as if the robot were straight, the
  port kept: "arm IK first"), then the robot's own step with the arm held.

Printed (and in ``summary.json``): tip position error [mm] and rotation error [°] (RMS, max) over the path,
joint motion (arm Σ|Δθ| [rad], robot Σ|Δq| [mm]), steps with a variable at a limit, limit violations of the
commanded joints (the model's own check from the joints: must be 0), the port's worst excursion [mm].
``track_port.rrd``: both schemes side by side (arm as link capsules and frames, the backbone, the target
path (blue) and the tracked path (orange), the port), the error curves.

    .venv/bin/python examples/track_port.py                  # ~1 min on a laptop CPU
    .venv/bin/rerun runs/track_port/track_port.rrd
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
from pytorch_kinematics.transforms import axis_angle_to_quaternion, matrix_to_axis_angle, quaternion_to_matrix

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn.arm import Composite  # noqa: E402
from dacr_learn.arm.control import DecoupledController, Port, WholeBodyConfig, WholeBodyController  # noqa: E402
from dacr_learn.cli.loading import composite_from_files  # noqa: E402
from dacr_learn.ik import ConstantCurvature  # noqa: E402
from dacr_learn.kinematics import backbone_points  # noqa: E402
from dacr_learn.viz.arm import log_arm, log_port  # noqa: E402
from dacr_learn.viz.layout import full_range_plot, time_panel_at_end  # noqa: E402
from dacr_learn.viz.scene import log_frames, log_path  # noqa: E402

F64 = torch.float64
PANDA_READY = (0.0, -0.3, 0.0, -2.2, 0.0, 2.0, math.pi / 4)     # the flange pointing down, in front of the base
SCHEMES = {"whole_body": "whole body", "decoupled": "decoupled (arm first)"}
TARGET_COLOR, TRACKED_COLOR, BACKBONE_COLOR = (40, 90, 230), (240, 120, 0), (250, 200, 70)
SPACING = 0.8          # [m] in y between the schemes' scenes
TIMELINE = "step"


def rotation_about(axis: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) [rad]."""
    return quaternion_to_matrix(axis_angle_to_quaternion(axis))


def port_path(base: torch.Tensor, steps: int, circle: float, depth: float, tilt: float) -> torch.Tensor:
    """Tip poses (steps, 4, 4): a circle of radius ``circle`` [m] at ``depth`` [m] along the robot base's z axis
    (base (4, 4), the start), the base orientation tilted by ``tilt`` [rad] outwards (about the tangent)."""
    t = 2 * math.pi * torch.arange(steps, dtype=F64) / steps
    ex, ey, ez = base[:3, 0], base[:3, 1], base[:3, 2]
    radial = torch.cos(t)[:, None] * ex + torch.sin(t)[:, None] * ey
    tangent = -torch.sin(t)[:, None] * ex + torch.cos(t)[:, None] * ey
    poses = torch.eye(4, dtype=F64).repeat(steps, 1, 1)
    poses[:, :3, :3] = rotation_about(-tilt * tangent) @ base[:3, :3]
    poses[:, :3, 3] = base[:3, 3] + depth * ez + circle * radial
    return poses


def feedforward(path: torch.Tensor) -> torch.Tensor:
    """(S, 6): the target's displacement to the next step (Δp [m], Δφ [rad], base frame); 0 at the end."""
    nxt = torch.cat([path[1:], path[-1:]])
    return torch.cat([nxt[:, :3, 3] - path[:, :3, 3], matrix_to_axis_angle(nxt[:, :3, :3] @ path[:, :3, :3].mT)], -1)


def run(model: Composite, controller, q0: torch.Tensor, path: torch.Tensor, settle: int,
        centre: torch.Tensor) -> dict[str, np.ndarray]:
    """Settle on path[0] for ``settle`` steps, then track the path: at step i the state is measured against
    target i, then commanded towards it with the feedforward to target i + 1. The tracking phase's arrays."""
    ff = feedforward(path)
    q, rows = q0[None].clone(), {k: [] for k in ("q", "x", "tip", "position_error", "rotation_error", "at_limit",
                                                 "inside", "port")}
    for k in range(settle + len(path)):
        i = max(0, k - settle)
        if k >= settle:                                      # the state at the time of target i, before its step
            check = model.check(q)
            x = model.variables(q)
            tip = torch.eye(4, dtype=F64)[None].clone()
            tip[:, :3, :3], tip[:, :3, 3] = check.rotation, check.position
            rows["q"].append(q[0])
            rows["x"].append(x[0])
            rows["tip"].append(tip[0])
            rows["position_error"].append((check.position[0] - path[i, :3, 3]).norm())
            rows["rotation_error"].append(matrix_to_axis_angle(check.rotation[0] @ path[i, :3, :3].mT).norm())
            rows["at_limit"].append(at_limit(model, x)[0])
            rows["inside"].append(check.inside[0] & (check.constraint[0] <= 1e-9))
            rows["port"].append((model.base_pose(x[:, :model.num_arm])[0, :3, 3] - centre).norm())
        q = controller.step(q, path[i:i + 1], ff[i:i + 1] if k >= settle else None)
    return {k: torch.stack(v).numpy() for k, v in rows.items()}


def at_limit(model: Composite, x: torch.Tensor, margin: float = 1e-9) -> torch.Tensor:
    """(B,) True where some variable lies on its bound (a box face, a disk rim) within ``margin`` of its scale."""
    lim = model.limits
    tol = margin * lim.scale
    hit = ((x <= lim.lower + tol) | (x >= lim.upper - tol)).any(-1)
    if lim.disks.numel():
        hit |= (torch.linalg.vector_norm(x[:, lim.disks], dim=-1) >= lim.radius * (1 - margin)).any(-1)
    return hit


def metrics(result: dict[str, np.ndarray], num_arm: int, port_radius: float) -> dict[str, float]:
    pe, re = 1e3 * result["position_error"], np.degrees(result["rotation_error"])
    q = result["q"]
    return {"position_rms_mm": float(np.sqrt(np.mean(pe**2))), "position_max_mm": float(pe.max()),
            "rotation_rms_deg": float(np.sqrt(np.mean(re**2))), "rotation_max_deg": float(re.max()),
            "arm_motion_rad": float(np.abs(np.diff(q[:, :num_arm], axis=0)).sum()),
            "robot_motion_mm": float(1e3 * np.abs(np.diff(q[:, num_arm:], axis=0)).sum()),
            "steps_at_a_limit": int(result["at_limit"].sum()), "steps": len(q),
            "limit_violations": int((~result["inside"]).sum()),
            "port_max_mm": float(1e3 * result["port"].max()), "port_radius_mm": 1e3 * port_radius}


def blueprint(summary: dict) -> rrb.Blueprint:
    eye = rrb.EyeControls3D(position=[1.35, -0.75, 0.95], look_target=[0.25, 0.5 * SPACING, 0.25],
                            eye_up=[0.0, 0.0, 1.0])
    scene = rrb.Spatial3DView(origin="scene", eye_controls=eye,
                              name="left: whole body · right: decoupled — target path (blue), tracked (orange), "
                                   "robot (yellow), port (red, in a plate)")
    res = summary["results"]
    plots = [full_range_plot(TIMELINE, origin=f"metrics/{quantity}", from_zero=True,
                             name=f"tip {label}: " + ", ".join(f"{SCHEMES[s]} RMS {res[s][key]:.3g}" for s in res))
             for quantity, label, key in (("position_error_mm", "position error [mm]", "position_rms_mm"),
                                          ("rotation_error_deg", "rotation error [°]", "rotation_rms_deg"))]
    return rrb.Blueprint(rrb.Horizontal(scene, rrb.Vertical(*plots), column_shares=[3, 2]),
                         time_panel_at_end(TIMELINE), collapse_panels=True)


def write_recording(path: Path, model: Composite, results: dict, target: torch.Tensor, port: Port,
                    axis: np.ndarray, summary: dict, every: int) -> None:
    """track_port.rrd: per scheme (shifted by SPACING in y) the port (a ball of its radius in a plate across
    ``axis``), the target and tracked paths, and every ``every`` steps the arm, the backbone, the tip and
    target frames; the error curves of both schemes."""
    rec = rr.RecordingStream("dacr_track_port")
    rec.set_sinks(rr.FileSink(str(path)), default_blueprint=blueprint(summary))
    rec.log("scene", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    colours = {"whole_body": (40, 160, 90), "decoupled": (200, 60, 60)}
    for j, (name, result) in enumerate(results.items()):
        root = f"scene/{name}"
        rec.log(root, rr.Transform3D(translation=[0.0, SPACING * j, 0.0]), static=True)
        rec.set_time(TIMELINE, sequence=0)                   # the paths from the first step on
        log_port(rec, f"{root}/port", port.centre, port.radius, axis=axis, wall=0.06)
        log_path(rec, f"{root}/target_path", target[:, :3, 3], color=TARGET_COLOR, radius=0.0015)
        log_path(rec, f"{root}/tracked_path", result["tip"][:, :3, 3], color=TRACKED_COLOR, radius=0.0008)
        title = np.asarray(target[:, :3, 3].amax(0)) + [0.0, 0.0, 0.35]
        rec.log(f"{root}/title", rr.Points3D([title], labels=[SCHEMES[name]], show_labels=True, radii=0.002,
                                             colors=colours[name]), static=True)
        x = torch.from_numpy(result["x"])
        n = model.num_arm
        frames = model.arm.frames(x[:, :n])
        bases = model.base_pose(x[:, :n])
        for k in range(0, len(x), every):
            rec.set_time(TIMELINE, sequence=k)
            log_arm(rec, f"{root}/arm", frames[k], mount=bases[k])
            if isinstance(model.robot, ConstantCurvature):
                f = model.robot.features(x[k:k + 1, n:])[0]
                pts = backbone_points(model.robot.spec, f, 12)
                world = pts @ bases[k, :3, :3].T + bases[k, :3, 3]
                log_path(rec, f"{root}/backbone", world, color=BACKBONE_COLOR, radius=0.004)
            log_frames(rec, f"{root}/tip", result["tip"][k:k + 1], axis_length=0.04)
            log_frames(rec, f"{root}/target", target[k:k + 1].numpy(), axis_length=0.04, radius=0.0015)
        for quantity, values in (("position_error_mm", 1e3 * result["position_error"]),
                                 ("rotation_error_deg", np.degrees(result["rotation_error"]))):
            entity = f"metrics/{quantity}/{name}"
            rec.log(entity, rr.SeriesLines(names=[SCHEMES[name]], colors=[colours[name]]), static=True)
            rec.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, sequence=np.arange(len(values)))],
                             columns=rr.Scalars.columns(scalars=values))
    rec.disconnect()


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arm", default=str(ROOT / "configs" / "arms" / "panda.urdf"))
    p.add_argument("--arm-tip", default="panda_link8")
    p.add_argument("--mount", default=str(ROOT / "configs" / "arms" / "panda_mount.npy"))
    p.add_argument("--robot", default=str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"))
    p.add_argument("--ready", type=float, nargs="+", help="the arm's start (default: the Panda's ready pose, "
                   "else the middle of its joint ranges)")
    p.add_argument("--steps", type=int, default=400, help="control steps for one lap of the path")
    p.add_argument("--settle", type=int, default=150, help="steps on the path's first pose before the lap")
    p.add_argument("--circle", type=float, default=0.08, help="radius of the tip's circle [m]")
    p.add_argument("--depth", type=float, default=0.22, help="depth of the circle behind the port [m]")
    p.add_argument("--tilt", type=float, default=0.7, help="the tip's outward tilt [rad]")
    p.add_argument("--port-radius", type=float, default=0.005, help="[m]")
    p.add_argument("--gain", type=float, default=0.5)
    p.add_argument("--every", type=int, default=4, help="log the bodies every this many steps")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "track_port")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(1)
    model = composite_from_files(args.arm, args.arm_tip, args.mount, args.robot)
    n = model.num_arm
    ready = args.ready or (PANDA_READY if model.arm.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
                           else model.home.tolist())
    ready = model.limits.project(torch.cat([torch.tensor(ready, dtype=F64), model.robot.rest.to(F64)]))[:n]
    q0 = model.joints(torch.cat([ready, model.robot.rest.to(F64)])[None])[0]
    base = model.base_pose(ready[None])[0]
    port = Port(tuple(base[:3, 3].tolist()), args.port_radius)
    path = port_path(base, args.steps, args.circle, args.depth, args.tilt)
    config = WholeBodyConfig(gain=args.gain)
    controllers = {"whole_body": WholeBodyController(model, config, port),
                   "decoupled": DecoupledController(model, config, port)}
    results = {name: run(model, c, q0, path, args.settle, base[:3, 3]) for name, c in controllers.items()}
    summary = {"arm": args.arm, "arm_tip": args.arm_tip, "robot": args.robot, "steps": args.steps,
               "settle": args.settle, "path": {"circle_m": args.circle, "depth_m": args.depth, "tilt_rad": args.tilt},
               "config": {"gain": config.gain, "damping": config.damping, "max_step": config.max_step},
               "results": {name: metrics(r, n, args.port_radius) for name, r in results.items()}}
    args.out.mkdir(parents=True, exist_ok=True)
    write_recording(args.out / "track_port.rrd", model, results, path, port, base[:3, 2].numpy(), summary,
                    args.every)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, args.out)
    return summary


def print_summary(summary: dict, out: Path) -> None:
    print(f"\ntip path behind a {summary['results']['whole_body']['port_radius_mm']:.0f} mm port, "
          f"{summary['steps']} steps")
    head = ("scheme", "pos RMS mm", "pos max mm", "rot RMS °", "rot max °", "arm rad", "robot mm", "at limit",
            "violations", "port max mm")
    print("  " + " ".join(f"{h:>12}" for h in head))
    for name, r in summary["results"].items():
        vals = (r["position_rms_mm"], r["position_max_mm"], r["rotation_rms_deg"], r["rotation_max_deg"],
                r["arm_motion_rad"], r["robot_motion_mm"])
        print(f"  {name:>12} " + " ".join(f"{v:>12.3f}" for v in vals)
              + f" {r['steps_at_a_limit']:>12d} {r['limit_violations']:>12d} {r['port_max_mm']:>12.3f}")
    print(f"  Rerun: .venv/bin/rerun {out / 'track_port.rrd'}   summary: {out / 'summary.json'}")


if __name__ == "__main__":
    main()
