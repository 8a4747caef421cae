"""Collision-free IK on the shipped scenes, side by side with the plain solver on the same targets.

    python benchmarks/ik_scene.py [--targets 1000] [--solutions 8] [--clearance 0.005] [--threads 2]

Scenes: configs/scenes/spheres_tdcr3.yaml (20 spheres around the 3-segment robot) and
configs/scenes/port_panda.yaml (a port in a wall and a sphere behind it, the robot on the Panda). Targets: tip
poses of random configurations whose body (and the arm's links) clears the scene by at least the clearance (for
the arm: its joints within ±0.15 rad of home, so that many reach through the port). Each flagged solution is
re-checked independently: the joints' features (encoder) → the classic arc formula in NumPy at 400 points per
segment → NumPy distances to the obstacles by projection, minus the body radius (the arm's link capsules,
posed by pytorch-kinematics, densely sampled as well). Prints per scene: targets solved, false flags, distinct
solutions per target, verified solutions/s, and the plain solver's time on the same targets.
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
sys.path.insert(0, str(ROOT / "tests"))          # the independent NumPy references

from conftest import reference_backbone  # noqa: E402

from dacr_learn.arm import Composite, load_arm  # noqa: E402
from dacr_learn.ik import ConstantCurvature, solve_ik  # noqa: E402
from dacr_learn.ik.collision import Avoidance  # noqa: E402
from dacr_learn.layers import ClarkeEncoder  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402
from dacr_learn.scene import load_scene  # noqa: E402

F64 = torch.float64


def numpy_scene_distance(scene, points: np.ndarray) -> np.ndarray:
    """Smallest signed distance (N,) of points to the scene's spheres and boxes, by projection."""
    out = np.full(points.shape[0], np.inf)
    for c, r in zip(scene.sphere_center.numpy(), scene.sphere_radius.numpy(), strict=True):
        out = np.minimum(out, np.linalg.norm(points - c, axis=-1) - r)
    for c, rot, half in zip(scene.box_center.numpy(), scene.box_rotation.numpy(), scene.box_half.numpy(), strict=True):
        local = (points - c) @ rot
        outside = np.linalg.norm(local - np.clip(local, -half, half), axis=-1)
        out = np.minimum(out, np.where(outside > 0, outside, -np.min(half - np.abs(local), axis=-1)))
    return out


def numpy_clearance(model, spec: RobotSpec, scene, q: np.ndarray) -> np.ndarray:
    """Independent clearance (B,) of joint vectors (B, N): dense NumPy arcs (and link capsules) to the obstacles."""
    n_arm = getattr(model, "num_arm", 0)
    f = ClarkeEncoder(spec).to(F64)(torch.from_numpy(q[:, n_arm:])).numpy()
    radius = np.concatenate([[spec.segments[0].body_radius]] + [[s.body_radius] * 400 for s in spec.segments])
    out = np.empty(q.shape[0])
    if n_arm:
        theta = torch.from_numpy(q[:, :n_arm])
        base = (model.base_pose(theta)).numpy()
        a, b, r, near = (t.numpy() for t in model.links(model.variables(torch.from_numpy(q))))
    for i in range(q.shape[0]):
        pts = reference_backbone(spec, f[i], 400)
        if n_arm:
            pts = pts @ base[i, :3, :3].T + base[i, :3, 3]
        c = (numpy_scene_distance(scene, pts) - radius).min()
        if n_arm:
            t = np.linspace(0, 1, 200)[:, None]
            for j in range(a.shape[1]):
                link = a[i, j] + t * (b[i, j] - a[i, j])
                c = min(c, numpy_scene_distance(scene, link).min() - r[j])
                if not near[j]:
                    u = np.clip((pts - a[i, j]) @ (b[i, j] - a[i, j]) / max(np.sum((b[i, j] - a[i, j]) ** 2), 1e-300),
                                0, 1)
                    c = min(c, (np.linalg.norm(pts - (a[i, j] + u[:, None] * (b[i, j] - a[i, j])), axis=-1)
                                - r[j] - radius).min())
        out[i] = c
    return out


def targets_for(model, scene, clearance: float, n: int, seed: int, arm_spread: float | None) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    avoid, found = Avoidance(model, scene, clearance), []
    while sum(len(x) for x in found) < n:
        x = model.limits.sample(4 * n, gen)
        if arm_spread is not None:
            x[:, :model.num_arm] = (model.home + arm_spread * (2 * torch.rand(4 * n, model.num_arm, generator=gen,
                                                                              dtype=F64) - 1))
            x[:, :model.num_arm] = torch.clamp(x[:, :model.num_arm], model.arm.limits.lower, model.arm.limits.upper)
        found.append(x[avoid.clearance_of(x) >= clearance])
    x = torch.cat(found)[:n]
    pos, rot, _ = model.tip_and_jacobian(x)
    t = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    t[:, :3, :3], t[:, :3, 3] = rot, pos
    return t


def run(name: str, model, spec: RobotSpec, scene_file: Path, args, arm_spread: float | None) -> None:
    scene = load_scene(scene_file)
    targets = targets_for(model, scene, args.clearance, args.targets, 0, arm_spread)
    seeds = (lambda t: model.seeds(t, args.solutions)) if hasattr(model, "seeds") else (lambda t: None)
    started = time.perf_counter()
    plain = solve_ik(model, targets, args.solutions, seeds=seeds(targets))
    t_plain = time.perf_counter() - started
    started = time.perf_counter()
    res = solve_ik(model, targets, args.solutions, seeds=seeds(targets), scene=scene, clearance=args.clearance)
    t_scene = time.perf_counter() - started
    ok = res.success
    flagged = ok.nonzero().tolist()
    q = res.q[ok].numpy()
    true = numpy_clearance(model, spec, scene, q) if len(q) else np.zeros(0)
    false = int((true < args.clearance).sum())
    b, k = ok.shape
    print(f"{name}: {b} targets clear by >= {args.clearance * 1e3:.1f} mm, K = {k}")
    print(f"  plain solver: {plain.success.any(1).double().mean() * 100:.1f} % solved, "
          f"{int(plain.success.sum())} solutions in {t_plain:.1f} s ({plain.success.sum() / t_plain:.0f} /s)")
    print(f"  with scene:   {ok.any(1).double().mean() * 100:.1f} % solved, {len(flagged)} solutions, "
          f"{false} false flags (dense NumPy check; smallest true clearance "
          f"{true.min() * 1e3 if len(true) else float('nan'):.3f} mm, reported ≤ true: "
          f"{bool((res.clearance[ok].numpy() <= true + 1e-12).all())}), "
          f"{res.distinct.sum(1).double().mean():.2f} distinct per target, {t_scene:.1f} s "
          f"({len(flagged) / t_scene:.0f} verified solutions/s; {t_scene / t_plain:.1f}x the plain solver)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--targets", type=int, default=1000)
    p.add_argument("--solutions", type=int, default=8)
    p.add_argument("--clearance", type=float, default=0.005)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--only", choices=["spheres", "port"])
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml")
    if args.only in (None, "spheres"):
        run("spheres around the 3-segment robot", ConstantCurvature(spec), spec,
            ROOT / "configs" / "scenes" / "spheres_tdcr3.yaml", args, None)
    if args.only in (None, "port"):
        arm = load_arm(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8")
        whole = Composite(arm, torch.from_numpy(np.load(ROOT / "configs" / "arms" / "panda_mount.npy")), spec)
        run("port and obstacle, robot on the Panda", whole, spec, ROOT / "configs" / "scenes" / "port_panda.yaml",
            args, 0.15)


if __name__ == "__main__":
    main()
