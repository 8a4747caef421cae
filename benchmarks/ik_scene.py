"""Collision-free IK on the shipped scenes, side by side with the plain solver on the same targets.

    python benchmarks/ik_scene.py [--targets 1000] [--solutions 8] [--clearance 0.005] [--threads 2] [--shards 2]

Scenes: configs/scenes/spheres_tdcr3.yaml (20 spheres around the 3-segment robot) and
configs/scenes/port_panda.yaml (a port in a wall and a sphere behind it, the robot on the Panda). Targets: tip
poses of random configurations whose body (and the arm's links) clears the scene by at least the clearance (for
the arm: its joints within ±0.15 rad of home, so that many reach through the port). Each flagged solution is
re-checked independently: the joints' features (encoder) → the classic arc formula in NumPy at 400 points per
segment → NumPy distances to the obstacles by projection, minus the body radius (the arm's link capsules,
posed by pytorch-kinematics, densely sampled as well). Prints per scene: targets solved, false flags, distinct
solutions per target, verified solutions/s, and the plain solver's time on the same targets (wall and CPU time of
the process, and the load average, side by side in one run). ``--shards N``: both solves split their targets into N
shards on parallel threads (``IKOptions.shards``; with ``--threads`` ≥ N).
"""
from __future__ import annotations

import argparse
import os
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
from dacr_learn.ik import ConstantCurvature, IKOptions, solve_ik  # noqa: E402
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


def rotations_z(a: np.ndarray) -> np.ndarray:
    """Rz(a) (B, 3, 3) of angles (B,)."""
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def rotations_y(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def dense_arcs(spec: RobotSpec, f: np.ndarray, n: int) -> np.ndarray:
    """Backbone points (B, 1 + m·n, 3) of features (B, m, 4) by the classic arc formula (Webster & Jones:
    R = Rz(θ)Ry(φ)Rz(−θ), p(s) = (β/φ)(cosθ(1 − cos sφ), sinθ(1 − cos sφ), sin sφ)), vectorised over samples
    and points (the per-point loop of tests/conftest.reference_backbone, which it is checked against)."""
    b, s = f.shape[0], np.arange(1, n + 1) / n
    rot, pos, out = np.tile(np.eye(3), (b, 1, 1)), np.zeros((b, 3)), [np.zeros((b, 1, 3))]
    for k, seg in enumerate(spec.segments):
        theta = np.arctan2(f[:, k, 1], f[:, k, 0])
        phi = np.hypot(f[:, k, 0], f[:, k, 1]) / seg.radius
        beta = f[:, k, 2] if seg.extends else np.full(b, seg.length)
        alpha = f[:, k, 3] if seg.twists else np.zeros(b)
        sp = s[None] * phi[:, None]                                                  # (B, n)
        bent = phi[:, None] > 0
        scale = np.where(phi > 0, beta / np.where(phi > 0, phi, 1.0), 0.0)[:, None]
        one_minus_cos = 2 * np.sin(sp / 2) ** 2
        local = np.stack([np.cos(theta)[:, None] * one_minus_cos * scale, np.sin(theta)[:, None] * one_minus_cos
                          * scale, np.where(bent, scale * np.sin(sp), s[None] * beta[:, None])], -1)  # (B, n, 3)
        frame = rot @ rotations_z(alpha)
        out.append(np.einsum("bij,bnj->bni", frame, local) + pos[:, None])
        pos = pos + np.einsum("bij,bj->bi", frame, local[:, -1])
        rot = frame @ rotations_z(theta) @ rotations_y(phi) @ rotations_z(-theta)
    return np.concatenate(out, 1)


def numpy_clearance(model, spec: RobotSpec, scene, q: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Independent clearance (B,) of joint vectors (B, N): dense NumPy arcs (and link capsules) to the obstacles."""
    n_arm = getattr(model, "num_arm", 0)
    f = ClarkeEncoder(spec).to(F64)(torch.from_numpy(q[:, n_arm:])).numpy()
    for i in range(min(3, len(f))):                              # the vectorised arcs are the per-point formula's
        assert np.abs(dense_arcs(spec, f[i:i + 1], 50)[0] - reference_backbone(spec, f[i], 50)).max() < 1e-12
    radius = np.concatenate([[spec.segments[0].body_radius]] + [[s.body_radius] * 400 for s in spec.segments])
    out = np.empty(q.shape[0])
    if n_arm:
        theta = torch.from_numpy(q[:, :n_arm])
        base = (model.base_pose(theta)).numpy()
        a, b, r, near = (t.numpy() for t in model.links(model.variables(torch.from_numpy(q))))
    t = np.linspace(0, 1, 200)[:, None]
    for start in range(0, q.shape[0], chunk):
        rows = slice(start, start + chunk)
        pts = dense_arcs(spec, f[rows], 400)                                         # (C, P, 3)
        if n_arm:
            pts = np.einsum("bij,bpj->bpi", base[rows, :3, :3], pts) + base[rows, None, :3, 3]
        c = (numpy_scene_distance(scene, pts.reshape(-1, 3)).reshape(pts.shape[:2]) - radius).min(-1)
        if n_arm:
            for j in range(a.shape[1]):
                ab = b[rows, j] - a[rows, j]                                            # (C, 3)
                link = a[rows, j][:, None] + t[None] * ab[:, None]                      # (C, 200, 3)
                c = np.minimum(c, numpy_scene_distance(scene, link.reshape(-1, 3)).reshape(link.shape[:2]).min(-1)
                               - r[j])
                if not near[j]:
                    u = np.clip(np.einsum("bpk,bk->bp", pts - a[rows, j][:, None], ab)
                                / np.maximum((ab * ab).sum(-1), 1e-300)[:, None], 0, 1)
                    gap = np.linalg.norm(pts - (a[rows, j][:, None] + u[..., None] * ab[:, None]), axis=-1)
                    c = np.minimum(c, (gap - r[j] - radius).min(-1))
        out[rows] = c
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
    options = IKOptions(shards=args.shards)
    solve_ik(model, targets[:8], args.solutions, seeds=seeds(targets[:8]), options=options, scene=scene,
             clearance=args.clearance)                                            # warm-up
    started, cpu = time.perf_counter(), time.process_time()
    plain = solve_ik(model, targets, args.solutions, seeds=seeds(targets), options=options)
    t_plain, c_plain = time.perf_counter() - started, time.process_time() - cpu
    started, cpu = time.perf_counter(), time.process_time()
    res = solve_ik(model, targets, args.solutions, seeds=seeds(targets), options=options, scene=scene,
                   clearance=args.clearance)
    t_scene, c_scene = time.perf_counter() - started, time.process_time() - cpu
    ok = res.success
    flagged = ok.nonzero().tolist()
    q = res.q[ok].numpy()
    true = numpy_clearance(model, spec, scene, q) if len(q) else np.zeros(0)
    false = int((true < args.clearance).sum())
    b, k = ok.shape
    print(f"{name}: {b} targets clear by >= {args.clearance * 1e3:.1f} mm, K = {k}, {args.threads} threads, "
          f"{args.shards} shards, load average {os.getloadavg()[0]:.1f}")
    print(f"  plain solver: {plain.success.any(1).double().mean() * 100:.1f} % solved, "
          f"{int(plain.success.sum())} solutions in {t_plain:.1f} s ({plain.success.sum() / t_plain:.0f} /s; CPU "
          f"{c_plain:.1f} s)")
    print(f"  with scene:   {ok.any(1).double().mean() * 100:.1f} % solved, {len(flagged)} solutions, "
          f"{false} false flags (dense NumPy check; smallest true clearance "
          f"{true.min() * 1e3 if len(true) else float('nan'):.3f} mm, reported ≤ true: "
          f"{bool((res.clearance[ok].numpy() <= true + 1e-12).all())}), "
          f"{res.distinct.sum(1).double().mean():.2f} distinct per target, {t_scene:.1f} s "
          f"({len(flagged) / t_scene:.0f} verified solutions/s; {t_scene / t_plain:.2f}x the plain solver; CPU "
          f"{c_scene:.1f} s, {c_scene / c_plain:.2f}x)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--targets", type=int, default=1000)
    p.add_argument("--solutions", type=int, default=8)
    p.add_argument("--clearance", type=float, default=0.005)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--shards", type=int, default=1, help="IKOptions.shards of both solves (parallel threads)")
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
