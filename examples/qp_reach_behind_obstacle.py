"""Reach behind an obstacle: constrained (QP) control side by side with today's resolved-rate controllers.

Two scenes, each from the same start along the same target path, with the same gains and every limit:

- ``robot``: the 3-segment TDCR (configs/robots/tdcr_3seg_coupled.yaml) on a fixed base; a sphere stands beside
  its upper half and the tip target moves from the straight tip to a point behind the sphere. Compared:
  :class:`dacr_learn.deploy.control.ResolvedRateController` (damped least squares, limits by saturation) and
  :class:`dacr_learn.deploy.qp_control.QPController` (one QP per step: limits, joint speeds, clearance dampers).
- ``arm``: the Panda holds the robot through a 5 mm port (as in examples/track_port.py); the tip tracks a circle
  behind the port while a sphere sits inside the cone the body sweeps. Compared:
  :class:`~dacr_learn.arm.control.WholeBodyController`, :class:`~dacr_learn.arm.control.DecoupledController` and
  :class:`~dacr_learn.arm.qp_control.WholeBodyQPController`, all with the Panda's URDF velocity limits at
  ``--dt`` (10 ms).

The obstacle distances come from a minimal sphere scene in this file (:class:`SphereClearance`: the robot's
backbone points, :func:`dacr_learn.kinematics.backbone_points`, swept by the envelope radius); the controllers take any
provider x → (d, ∂d/∂x). Printed per controller (and in ``summary.json``): collision steps and the minimum
clearance [mm] (a dense check: 64 points per segment), the tip position error (RMS, max) [mm] over the path and
at its end, steps with a variable at a limit, limit violations of the commanded joints (the model's own check
from the joints), the port's worst excursion (arm scene) and the median step time [µs] (eager, batch 1).

    .venv/bin/python examples/qp_reach_behind_obstacle.py                 # both scenes, ~1-2 min on a laptop CPU
    .venv/bin/python examples/qp_reach_behind_obstacle.py --scene robot
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
from dacr_learn.kinematics import backbone_points  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402

F64 = torch.float64
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
PANDA_READY = (0.0, -0.3, 0.0, -2.2, 0.0, 2.0, math.pi / 4)
ENVELOPE = 0.008        # [m] the robot's body radius: its largest joint radius (the spacer disks)


class SphereClearance:
    """Clearance of a body to spheres: d_jk = ‖p_j − c_k‖ − r_k − a [m] for body points p_j = ``points(x)``
    (B, P, 3) with envelope radius a, spheres (centres (K, 3), radii (K,)); ∂d/∂x (B, P·K, D) by central
    differences of the points with steps 1e-5 of each variable's ``scale`` (relative error ~1e-10 in float64).
    ``__call__`` is the controllers' distance provider; :meth:`clearance` the distances alone."""

    def __init__(self, points: Callable[[torch.Tensor], torch.Tensor], centres, radii, envelope: float,
                 scale: torch.Tensor):
        self.points, self.envelope = points, envelope
        self.centres, self.radii = torch.as_tensor(centres, dtype=F64), torch.as_tensor(radii, dtype=F64)
        self.steps = 1e-5 * scale.to(F64)

    def of_points(self, p: torch.Tensor) -> torch.Tensor:
        d = torch.linalg.vector_norm(p.unsqueeze(-2) - self.centres, dim=-1) - self.radii - self.envelope
        return d.flatten(-2)                                                      # (..., P·K)

    def clearance(self, x: torch.Tensor) -> torch.Tensor:
        return self.of_points(self.points(x))

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, dim = x.shape
        shift = torch.diag(self.steps)
        probe = torch.cat([x.unsqueeze(1), x.unsqueeze(1) + shift, x.unsqueeze(1) - shift], dim=1)
        pts = self.points(probe.reshape(-1, dim)).unflatten(0, (b, 2 * dim + 1))  # (B, 2D + 1, P, 3)
        centre, plus, minus = pts[:, 0], pts[:, 1:dim + 1], pts[:, dim + 1:]
        jac_p = ((plus - minus) / (2 * self.steps)[:, None, None]).permute(0, 2, 3, 1)   # (B, P, 3, D)
        diff = centre.unsqueeze(-2) - self.centres                                # (B, P, K, 3)
        norm = torch.linalg.vector_norm(diff, dim=-1, keepdim=True)
        d = (norm.squeeze(-1) - self.radii - self.envelope).flatten(1)
        jac = ((diff / norm).unsqueeze(-1) * jac_p.unsqueeze(2)).sum(-2)          # (B, P, K, D)
        return d, jac.flatten(1, 2)


def cc_jacobian(model: ConstantCurvature) -> Callable:
    """The closed-form CC Jacobian as :class:`ResolvedRateController` takes it: q (B, N) → (pose, J_f, None)."""
    def jacobian(q: torch.Tensor):
        position, rotation, jac = model.tip_and_jacobian(model.variables(q))
        pose = torch.eye(4, dtype=F64).repeat(len(q), 1, 1)
        pose[:, :3, :3], pose[:, :3, 3] = rotation, position
        return pose, jac, None
    return jacobian


def robot_points(model: ConstantCurvature, per_segment: int) -> Callable[[torch.Tensor], torch.Tensor]:
    return lambda x: backbone_points(model.spec, model.features(x), per_segment)


def arm_points(model, per_segment: int) -> Callable[[torch.Tensor], torch.Tensor]:
    """The robot's backbone in the arm's base frame: x (B, n + D) → (B, P, 3)."""
    n = model.num_arm

    def points(x: torch.Tensor) -> torch.Tensor:
        base = model.base_pose(x[:, :n])
        local = backbone_points(model.robot.spec, model.robot.features(x[:, n:]), per_segment)
        return local @ base[:, :3, :3].mT + base[:, None, :3, 3]
    return points


def at_limit(limits, x: torch.Tensor, margin: float = 1e-6) -> torch.Tensor:
    """(B,) True where some variable lies within ``margin`` of its scale of a bound (a box face, a disk rim)."""
    tol = margin * limits.scale
    hit = ((x <= limits.lower + tol) | (x >= limits.upper - tol)).any(-1)
    if limits.disks.numel():
        hit |= (torch.linalg.vector_norm(x[:, limits.disks], dim=-1) >= limits.radius * (1 - margin)).any(-1)
    return hit


def run(model, controller, q0: torch.Tensor, path: torch.Tensor, check: SphereClearance,
        port: Port | None = None) -> dict:
    """Track ``path`` (S, 3) or (S, 4, 4) from q0 (N,); the state at step i is measured against target i, then
    commanded towards it with the feedforward to target i + 1. Metrics of the whole run."""
    pos_path = path if path.dim() == 2 else path[:, :3, 3]
    nxt = torch.cat([pos_path[1:], pos_path[-1:]])
    q, rows = q0[None].clone(), {k: [] for k in ("error", "clearance", "at_limit", "inside", "port", "time")}
    for i in range(len(path)):
        c = model.check(q)
        x = model.variables(q)
        rows["error"].append(float((c.position[0] - pos_path[i]).norm()))
        rows["clearance"].append(float(check.clearance(x).min()))
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
    return out


def ramp(start: torch.Tensor, goal: torch.Tensor, move: int, hold: int) -> torch.Tensor:
    """(move + hold, 3): a smooth (cosine) move from start to goal, then ``hold`` steps at the goal."""
    s = 0.5 - 0.5 * torch.cos(math.pi * torch.arange(1, move + 1, dtype=F64) / move)
    return torch.cat([start + s[:, None] * (goal - start), goal.expand(hold, 3)])


def robot_setup(args) -> dict:
    """The robot alone: a sphere beside its upper half, the tip target behind it. The model, the controllers, the
    start q0 (N,), the target path (S, 3), the dense clearance check and the sphere."""
    spec = RobotSpec.coerce(args.robot)
    model = ConstantCurvature(spec)
    length = spec.total_length
    sphere = ([0.26 * length, 0.0, 0.7 * length], 0.09 * length)
    goal = torch.tensor([0.65 * length, 0.05 * length, 0.55 * length], dtype=F64)
    path = ramp(model.tip_and_jacobian(model.rest[None])[0][0], goal, args.steps, args.hold)
    sensed = SphereClearance(robot_points(model, args.points), [sphere[0]], [sphere[1]], ENVELOPE,
                             model.limits.scale)
    controllers = {"resolved_rate": ResolvedRateController(spec, cc_jacobian(model), ControllerConfig(
                       gain=args.gain, damping=QPConfig().damping, max_step=args.max_step)),
                   "qp": QPController(model, qp_config(args), sensed)}
    return {"model": model, "controllers": controllers, "q0": model.joints(model.rest[None])[0], "path": path,
            "check": SphereClearance(robot_points(model, 64), [sphere[0]], [sphere[1]], ENVELOPE, model.limits.scale),
            "sphere": {"centre_m": sphere[0], "radius_m": sphere[1]}}


def arm_setup(args) -> dict:
    """The Panda through a port; the tip circles behind it, a sphere inside the cone the body sweeps (as
    :func:`robot_setup`, the path (S, 3), and the port)."""
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
    sphere = ((base[:3, 3] + 0.19 * ez + 0.03 * ey).tolist(), 0.012)      # inside the cone the body sweeps
    sensed = SphereClearance(arm_points(model, args.points), [sphere[0]], [sphere[1]], ENVELOPE, model.limits.scale)
    wb = WholeBodyConfig(gain=args.gain, max_step=args.max_step, dt=args.dt)
    controllers = {"whole_body": WholeBodyController(model, wb, port),
                   "decoupled": DecoupledController(model, wb, port),
                   "whole_body_qp": WholeBodyQPController(model, qp_config(args), port, sensed, dt=args.dt)}
    return {"model": model, "controllers": controllers, "q0": model.joints(x0[None])[0], "path": path,
            "check": SphereClearance(arm_points(model, 64), [sphere[0]], [sphere[1]], ENVELOPE, model.limits.scale),
            "sphere": {"centre_m": sphere[0], "radius_m": sphere[1]}, "port": port}


def qp_config(args) -> QPConfig:
    return QPConfig(gain=args.gain, max_step=args.max_step, safety=args.safety, influence=args.influence,
                    damper_gain=args.damper_gain, joint_step=args.joint_step)


def run_scene(setup: dict) -> dict:
    """Every controller of a setup over its path (:func:`run`)."""
    port = setup.get("port")
    results = {k: run(setup["model"], c, setup["q0"], setup["path"], setup["check"], port)
               for k, c in setup["controllers"].items()}
    return {"sphere": setup["sphere"], **({"port_radius_mm": 1e3 * port.radius} if port else {}),
            "results": results}


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
    p.add_argument("--points", type=int, default=16, help="body points per segment the QP sees")
    p.add_argument("--dt", type=float, default=0.01, help="control period [s] for the arm's URDF velocity limits")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "qp_reach")
    return p.parse_args(argv)


def print_table(name: str, scene: dict) -> None:
    print(f"\n{name}: sphere r = {1e3 * scene['sphere']['radius_m']:.1f} mm")
    cols = [("collisions", "collisions", "d"), ("min_clearance_mm", "min clear mm", ".2f"),
            ("error_rms_mm", "err RMS mm", ".2f"), ("error_max_mm", "err max mm", ".2f"),
            ("final_error_mm", "err end mm", ".2f"), ("steps_at_a_limit", "at limit", "d"),
            ("limit_violations", "violations", "d"), ("port_max_mm", "port max mm", ".3f"),
            ("step_p50_us", "step p50 µs", ".0f")]
    cols = [c for c in cols if c[0] in next(iter(scene["results"].values()))]
    print("  " + f"{'controller':>14}" + "".join(f"{h:>14}" for _, h, _ in cols))
    for ctrl, r in scene["results"].items():
        print("  " + f"{ctrl:>14}" + "".join(f"{r[k]:>14{f}}" for k, _, f in cols))


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(1)
    summary = {"config": {k: v for k, v in vars(args).items() if k != "out"}}
    for name, setup in (("robot", robot_setup), ("arm", arm_setup)):
        if args.scene in (name, "both"):
            summary[name] = run_scene(setup(args))
            print_table(name, summary[name])
    summary["config"]["robot"] = str(args.robot)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    main()
