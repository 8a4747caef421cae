"""The peer planner's side of benchmarks/ftl.py, run with a Python that has numpy, scipy and scikit-learn (the
benchmark's own virtual environment, or --peer-python): nothing of dacr_learn is imported here.

    python benchmarks/ftl_peer.py curves  --peer PEER_DIR --out DIR [--per-class 40] [--seed 0]
    python benchmarks/ftl_peer.py library --peer PEER_DIR --out DIR [--library 10000] [--seed 0]
    python benchmarks/ftl_peer.py plan    --peer PEER_DIR --out DIR --curve I

``curves`` draws the benchmark's curves with the peer's own generators (src/PathGenerators: a quadratic Bézier
through a control point, its S shape, its C shape; end and control points uniformly within ±0.3 of the defaults of
its run_example.py, the C shape's radial angle normally, σ = 20°), each twice: with the peer's waypoint count (its
input) and densely (the path our planner takes and both are scored on): curves.npz.

``library`` builds the peer's threshold-cluster planner once for the robot (its shape library and clusters, the
run_example.py defaults, generated in parallel on all cores as the peer does by default) and pickles it:
library.pkl, library.json (its wall time).

``plan`` loads the pickled planner and plans curve I on one core: follow_path on the waypoints, then
interpolate_mp (40 steps between waypoints); writes peer_<I>.npz (per dense step: Clarke coordinates, base position
and orientation, the peer's own tip) and prints one JSON line (planning wall and CPU time, load time).
"""
from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

CLASSES = ("bezier", "s", "c")


def arc_through(points: np.ndarray, n: int) -> np.ndarray:
    """n points on the circular arc through points[0], points[len // 2], points[-1] (its C shape is an arc)."""
    a, b, c = points[0], points[len(points) // 2], points[-1]
    ab, ac = b - a, c - a
    normal = np.cross(ab, ac)
    centre = a + (np.dot(ac, ac) * np.cross(normal, ab) + np.dot(ab, ab) * np.cross(ac, normal)) / (
        2 * np.dot(normal, normal))
    u = (a - centre) / np.linalg.norm(a - centre)
    w = np.cross(normal / np.linalg.norm(normal), u)
    end = np.arctan2(np.dot(c - centre, w), np.dot(c - centre, u)) % (2 * np.pi)
    theta = np.linspace(0.0, end, n)[:, None]
    radius = np.linalg.norm(a - centre)
    return centre + radius * (np.cos(theta) * u + np.sin(theta) * w)


def draw_curves(generator, rng: np.random.Generator, per_class: int, waypoints: int, dense: int) -> list[dict]:
    """per_class curves of each class: dict(kind, sparse (the generator's waypoints), dense (dense, 3) the same
    curve densely: the generator again for the Bézier curves, the arc through the waypoints for the C shape (the
    generator keeps the last 3/4 of its points, so another count starts elsewhere on the circle))."""
    curves = []
    spread = 0.3
    for kind in CLASSES:
        for _ in range(per_class):
            jitter = lambda c: np.asarray(c, float) + rng.uniform(-spread, spread, 3)  # noqa: E731
            if kind == "bezier":
                start, end, control = np.zeros(3), jitter([2, 0, 1.3]), jitter([0, 0, 1.6])
                sparse = generator.generate_curved_path(start, end, control, num_waypoints=waypoints)
                fine = generator.generate_curved_path(start, end, control, num_waypoints=dense)
            elif kind == "s":
                end = jitter([-2.3, 0, 0.8])
                sparse = generator.generate_s_shape_path(np.zeros(3), end, num_waypoints=waypoints)
                fine = generator.generate_s_shape_path(np.zeros(3), end, num_waypoints=dense)
            else:
                end, angle = jitter([-2.3, 0, 0.8]), rng.normal(0.0, 20.0)
                sparse = generator.generate_c_shape_path(np.zeros(3), end, radial_angle=angle,
                                                         num_waypoints=waypoints)
                fine = arc_through(sparse, dense)
            curves.append({"kind": kind, "sparse": sparse, "dense": fine})
    return curves


def robot():
    from src.RobotModels.ConstantCurvatureModel import ConstantCurvature
    return ConstantCurvature(num_segments=3, segment_lengths=[1, 1, 1], tendon_offset=[0.2, 0.2, 0.2],
                             points_resolution=0.05)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("command", choices=("curves", "library", "plan"))
    p.add_argument("--peer", required=True, help="the peer's source folder (holds src/)")
    p.add_argument("--out", required=True)
    p.add_argument("--per-class", type=int, default=40)
    p.add_argument("--library", type=int, default=10_000)
    p.add_argument("--waypoints", type=int, default=10)
    p.add_argument("--interpolation", type=int, default=40)
    p.add_argument("--dense", type=int, default=1001)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--curve", type=int)
    args = p.parse_args()
    sys.path.insert(0, str(Path(args.peer).resolve()))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.command == "curves":
        from src.PathGenerators.PathGenerator import TaskGenerator
        curves = draw_curves(TaskGenerator(robot()), np.random.default_rng(args.seed), args.per_class,
                             args.waypoints, args.dense)
        np.savez(out / "curves.npz", kinds=np.array([c["kind"] for c in curves]),
                 **{f"sparse_{i}": c["sparse"] for i, c in enumerate(curves)},
                 **{f"dense_{i}": c["dense"] for i, c in enumerate(curves)})
    elif args.command == "library":
        from src.MasterClass import GeneralPathFollower
        np.random.seed(args.seed)
        t0 = time.perf_counter()
        general = GeneralPathFollower(robot())
        general.get_sampling_threshold_cluster(num_samples=args.library, base_stability_weight=0.3,
                                               base_stability_weight_rot=0.3, similarity_threshold=2.5,
                                               random_seed=args.seed)
        library_s = time.perf_counter() - t0
        with open(out / "library.pkl", "wb") as f:
            pickle.dump(general, f)
        (out / "library.json").write_text(json.dumps({"library_s": library_s, "library": args.library}))
        print(json.dumps({"library_s": library_s}))
    else:
        t0 = time.perf_counter()
        with open(out / "library.pkl", "rb") as f:
            general = pickle.load(f)
        sparse = np.load(out / "curves.npz")[f"sparse_{args.curve}"]
        load_s = time.perf_counter() - t0
        t0, cpu = time.perf_counter(), time.process_time()
        history = general.curr_follower.follow_path(sparse, verbose=False)
        dense, _ = general.interpolate_mp(history, steps_per_waypoint=args.interpolation, enable_optimization=True,
                                          verbose=False)
        plan_s, cpu_s = time.perf_counter() - t0, time.process_time() - cpu
        np.savez(out / f"peer_{args.curve}.npz", clarke=np.array([h["clark_coords"] for h in dense]),
                 base_position=np.array([h["base_position"] for h in dense]),
                 base_orientation=np.array([h["base_orientation"] for h in dense]),
                 tip=np.array([h["actual_tip"] for h in dense]))
        print(json.dumps({"plan_s": plan_s, "cpu_s": cpu_s, "load_s": load_s}))


if __name__ == "__main__":
    main()
