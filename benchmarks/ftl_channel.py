"""Follow-the-leader through a narrow channel: the 3-segment robot on the Panda (configs/robots/tdcr_3seg_coupled.yaml,
configs/arms/panda.urdf, tip panda_link8, configs/arms/panda_mount.npy) along a curved path inside a tube of capsules.

    python benchmarks/ftl_channel.py [--write] [--clearance 0.001] [--gap 0.0015]

--write makes the channel's files (else they are read): configs/paths/channel_panda.npy, the path: an arc of radius
0.3 m, 0.18 m long, from the robot's tip at the arm's home pose (the middle of every joint range, the robot
straight) along the tip's axis, bending towards +y; configs/scenes/channel_panda.yaml, the channel: 8 pieces along
the arc, each a ring of 6 capsules (radius 3 mm) parallel to the piece's chord, their surfaces ``--gap`` beyond
the robot's envelope (8 mm) from the path (the chord's sagitta, 0.2 mm, eats into it at the pieces' middles).

Then plans the insertion twice (the planner API, as ``python -m dacr_learn.plan ftl ... --scene
configs/scenes/channel_panda.yaml --clearance D``): without the scene (its clearance measured after the fact), and
with it (the clearance hinges in every step); prints steps, success, tip error, shape deviation, the clearance
(the planner's check, and a dense one: 200 points per segment of the backbone to every capsule, exactly) and the
time.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dacr_learn.arm import Composite, load_arm  # noqa: E402
from dacr_learn.ik.collision import Avoidance  # noqa: E402
from dacr_learn.kinematics import backbone_points  # noqa: E402
from dacr_learn.plan import plan_ftl  # noqa: E402
from dacr_learn.scene import load_scene  # noqa: E402

PATH = ROOT / "configs" / "paths" / "channel_panda.npy"
SCENE = ROOT / "configs" / "scenes" / "channel_panda.yaml"
F64 = torch.float64
RADIUS, LENGTH, PIECES, RING, CAPSULE = 0.3, 0.18, 8, 6, 0.003


def panda() -> Composite:
    arm = load_arm(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8")
    return Composite(arm, torch.from_numpy(np.load(ROOT / "configs" / "arms" / "panda_mount.npy")),
                     ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml")


def write(model: Composite, gap: float) -> None:
    pos, rot, _ = model.tip_and_jacobian(model.rest[None].to(F64))
    p0, t0 = pos[0].numpy(), rot[0, :, 2].numpy()
    n0 = np.array([0.0, 1.0, 0.0]) - t0[1] * t0                               # bend towards +y
    n0 /= np.linalg.norm(n0)
    b0 = np.cross(t0, n0)
    arc = lambda a: p0 + RADIUS * (np.sin(a)[:, None] * t0 + (1 - np.cos(a))[:, None] * n0)  # noqa: E731
    angle = np.linspace(0.0, LENGTH / RADIUS, 181)                           # 1 mm spacing
    PATH.parent.mkdir(parents=True, exist_ok=True)
    np.save(PATH, arc(angle))
    ring = max(s.body_radius for s in model.robot.spec.segments) + gap + CAPSULE
    lines = ["# A channel for the 3-segment robot on the Panda (tdcr_3seg_coupled.yaml, panda.urdf tip panda_link8,",
             "# panda_mount.npy), in the arm's base frame [m]: made by benchmarks/ftl_channel.py --write around the",
             f"# path configs/paths/channel_panda.npy (an arc of radius {RADIUS} m, {LENGTH} m long, from the tip at",
             f"# the arm's home pose): {PIECES} pieces along it, each a ring of {RING} capsules of radius {CAPSULE} m",
             f"# parallel to the piece's chord, their surfaces {gap * 1e3:.1f} mm beyond the robot's envelope.",
             "obstacles:"]
    ends = np.linspace(0.0, LENGTH / RADIUS, PIECES + 1)
    for a, b in zip(ends[:-1], ends[1:], strict=True):
        mid = 0.5 * (a + b)
        normal = -np.sin(mid) * t0 + np.cos(mid) * n0                        # the arc's normal at the middle
        pa, pb = arc(np.array([a, b]))
        for k in range(RING):
            phi = 2 * np.pi * k / RING
            off = ring * (np.cos(phi) * normal + np.sin(phi) * b0)
            ca, cb = pa + off, pb + off
            lines.append(f"  - {{type: capsule, a: [{ca[0]:.6f}, {ca[1]:.6f}, {ca[2]:.6f}], "
                         f"b: [{cb[0]:.6f}, {cb[1]:.6f}, {cb[2]:.6f}], radius: {CAPSULE}}}")
    SCENE.parent.mkdir(parents=True, exist_ok=True)
    SCENE.write_text("\n".join(lines) + "\n")


def dense_clearance(model: Composite, q: torch.Tensor, scene_file: Path, per_segment: int = 200) -> np.ndarray:
    """The robot body's clearance (T,) [m] to the scene's capsules from the joints alone: the backbone at
    ``per_segment`` points per segment, each point's exact distance to each capsule axis, less both radii."""
    import yaml
    x = model.variables(q)
    n = model.num_arm
    pts = backbone_points(model.robot.spec, model.robot.features(x[:, n:]), per_segment)         # (T, P, 3)
    base = model.base_pose(x[:, :n])
    pts = (base[:, None, :3, 3] + pts @ base[:, :3, :3].mT).numpy()
    envelope = max(s.body_radius for s in model.robot.spec.segments)
    caps = yaml.safe_load(scene_file.read_text())["obstacles"]
    a = np.array([c["a"] for c in caps])
    d = np.array([c["b"] for c in caps]) - a
    rad = np.array([c["radius"] for c in caps])
    t = np.clip(np.einsum("tpoi,oi->tpo", pts[:, :, None] - a, d) / (d * d).sum(-1), 0.0, 1.0)
    gap = np.linalg.norm(pts[:, :, None] - a - t[..., None] * d, axis=-1) - rad
    return gap.min(axis=(1, 2)) - envelope


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--write", action="store_true", help="make the path and scene files (else read them)")
    p.add_argument("--gap", type=float, default=0.0015, help="with --write: channel gap beyond the envelope [m]")
    p.add_argument("--clearance", type=float, default=0.001)
    args = p.parse_args()
    torch.set_num_threads(1)
    model = panda()
    if args.write:
        write(model, args.gap)
    path = torch.from_numpy(np.load(PATH))
    scene = load_scene(SCENE)
    length = model.robot.length
    for label, kw in (("without the scene", {}), ("with the scene", {"scene": scene, "clearance": args.clearance})):
        t0 = time.perf_counter()
        plan = plan_ftl(model, path, **kw)
        seconds = time.perf_counter() - t0
        check = Avoidance(model, scene, args.clearance).clearance_of_joints(plan.q)
        dense = dense_clearance(model, plan.q, SCENE)
        mean, worst = (100 * float(v) / length for v in (plan.shape_dev.mean(), plan.shape_dev_max.max()))
        print(f"{label}: {plan.s.shape[0]} steps, {'success' if plan.success else 'FAILED: ' + plan.reason}; tip "
              f"error max {float(plan.tip_err.max()) / length:.1e} L; shape deviation mean {mean:.3f} %, max "
              f"{worst:.3f} % of L; clearance min {1e3 * float(check.min()):.3f} mm (dense check "
              f"{1e3 * dense.min():.3f} mm); "
              f"limits {'inside' if bool(model.check(plan.q).inside.all()) else 'VIOLATED'}; {seconds:.1f} s",
              flush=True)


if __name__ == "__main__":
    main()
