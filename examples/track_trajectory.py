"""Closed-loop trajectory tracking with a learned Jacobian (resolved-rate control in Clarke space).

A learned FK checkpoint is exported (dacr_learn.export) and its ``jacobian`` module drives a
:class:`dacr_learn.deploy.control.ResolvedRateController`. The "real" robot is the analytic
constant-curvature model, optionally with Gaussian joint noise on the executed joint lengths and
a model mismatch (a different joint radius, a different backbone length); its measured tip
position closes the loop. The tip tracks a circle and a figure-8; printed are the RMS / max
tracking errors in mm and % of the robot length, and everything is logged to Rerun
(``runs/track/track.rrd``: desired and actual paths, the robot's backbone and tip frame over
time, the error curves). The recording carries its layout (:func:`tracking_blueprint`): the 3D
scene beside one full-range error plot per trajectory, opening at the last step.

    .venv/bin/python train.py fit --config configs/fk_type1.yaml          # the model (~2-3 min)
    .venv/bin/python examples/track_trajectory.py --ckpt runs/fk_type1
    .venv/bin/python examples/track_trajectory.py --ckpt runs/fk_type1 \\
        --joint-noise 2e-5 --radius-scale 1.05 --length-scale 0.97      # noise + model mismatch
    .venv/bin/rerun runs/track/track.rrd

``--ckpt`` takes a checkpoint or a run folder (its newest version's last.ckpt). Without it the
example uses runs/fk_type1, or trains a quick small model
(``--no-train``: just print the training command).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn import export as dexport  # noqa: E402
from dacr_learn.deploy.control import ControllerConfig, ResolvedRateController, analytic_jacobian  # noqa: E402
from dacr_learn.kinematics import backbone_points, forward_kinematics  # noqa: E402
from dacr_learn.layers import ClarkeEncoder  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402
from dacr_learn.runs import find_checkpoint, load_checkpoint_model  # noqa: E402
from dacr_learn.viz.layout import full_range_plot, time_panel_at_end  # noqa: E402
from dacr_learn.viz.scene import log_path, log_scene  # noqa: E402

DEFAULT_RUN = ROOT / "runs" / "fk_type1"
TRAIN_COMMAND = [".venv/bin/python", "train.py", "fit", "--config", "configs/fk_type1.yaml"]
DESIRED_COLOR, ACTUAL_COLOR = (40, 90, 230), (240, 120, 0)
TRAJECTORIES = {"circle": "circle", "figure8": "figure-8"}   # name (entity paths, summary) -> title
SCENE_SPACING = 0.1                                          # [m] in x between the trajectories' scenes
TIMELINE = "step"


class SimulatedRobot:
    """The analytic CC robot: executes joint vectors (+ noise) with a possibly different radius / length."""

    def __init__(self, spec: RobotSpec, radius_scale: float = 1.0, length_scale: float = 1.0,
                 joint_noise: float = 0.0, seed: int = 0):
        d = spec.to_dict()
        for seg in d["segments"]:
            seg["radius"] *= radius_scale
            seg["length"] *= length_scale
            if "joint_radii" in seg:
                seg["joint_radii"] = [r * radius_scale for r in seg["joint_radii"]]
            if "length" in seg["limits"]:
                seg["limits"]["length"] = [v * length_scale for v in seg["limits"]["length"]]
        self.spec = RobotSpec.from_dict(d)
        self.encoder = ClarkeEncoder(self.spec).double()
        self.length_scale, self.joint_noise = length_scale, joint_noise
        self.generator = torch.Generator().manual_seed(seed)

    def features(self, q: torch.Tensor) -> torch.Tensor:
        """Executed features (m, 4): q + noise through the true robot's encoder; β of extending
        segments scaled by ``length_scale`` (the backbone is longer/shorter than the joints say)."""
        q = q + self.joint_noise * torch.randn(q.shape, generator=self.generator, dtype=q.dtype)
        f = self.encoder(q)
        return f * torch.tensor([1.0, 1.0, self.length_scale, 1.0], dtype=f.dtype)

    def pose(self, features: torch.Tensor) -> torch.Tensor:
        return forward_kinematics(self.spec, features)


def trajectory(kind: str, spec: RobotSpec, steps: int, period_steps: int) -> torch.Tensor:
    """Desired tip positions (steps, 3) [m]: a circle or a figure-8 in the plane z = 0.88 L."""
    length = spec.total_length
    t = 2 * math.pi * torch.arange(steps, dtype=torch.float64) / period_steps
    a, z = 0.3 * length, torch.full((steps,), 0.88 * length, dtype=torch.float64)
    if kind == "circle":
        return torch.stack([a * torch.cos(t), a * torch.sin(t), z], dim=-1)
    if kind == "figure8":
        return torch.stack([a * torch.sin(t), 0.5 * a * torch.sin(2 * t), z], dim=-1)
    raise ValueError(f"trajectory: expected 'circle' or 'figure8', got {kind!r}")


def run_scenario(ctrl: ResolvedRateController, robot: SimulatedRobot, path: torch.Tensor, settle: int) -> dict:
    """Settle on path[0], then track ``path``; returns the logged arrays (numpy) of the tracking phase."""
    q = ctrl.space.joints(torch.tensor(_straight(ctrl.spec), dtype=torch.float64))
    desired = torch.cat([path[:1].expand(settle, 3), path, path[-1:]])
    rows = {"desired": [], "actual": [], "q": [], "features": [], "step_us": []}
    for k in range(settle + len(path)):
        feats = robot.features(q)
        pose = robot.pose(feats)
        t0 = time.perf_counter()
        q_next = ctrl.step(q, desired[k], feedforward=desired[k + 1] - desired[k], measured=pose[:3, 3])
        step_us = (time.perf_counter() - t0) * 1e6
        if k >= settle:
            for key, v in (("desired", desired[k]), ("actual", pose[:3, 3]), ("q", q), ("features", feats),
                           ("step_us", torch.tensor(step_us))):
                rows[key].append(v)
        q = q_next
    return {k: torch.stack(v).numpy() for k, v in rows.items()}


def _straight(spec: RobotSpec) -> list[float]:
    """Actuated features of the straight robot at nominal length: ρ = 0, β = l, α = 0."""
    out = []
    for s in spec.segments:
        out += [0.0, 0.0] + ([s.length] if s.extends else []) + ([0.0] if s.twists else [])
    return out


def errors(result: dict, length: float) -> dict[str, float]:
    err = np.linalg.norm(result["actual"] - result["desired"], axis=-1)
    rms, mx = float(np.sqrt(np.mean(err**2))), float(err.max())
    return {"rms_mm": 1e3 * rms, "max_mm": 1e3 * mx, "rms_pct": 100 * rms / length, "max_pct": 100 * mx / length,
            "step_p50_us": float(np.median(result["step_us"]))}


def log_result(rec: rr.RecordingStream, name: str, offset: float, robot: SimulatedRobot, result: dict,
               every: int) -> None:
    """Desired/actual paths, the robot every ``every`` steps, the error curve; scene shifted by ``offset`` in x."""
    root, title = f"scene/{name}", TRAJECTORIES.get(name, name)
    rec.log(root, rr.Transform3D(translation=[offset, 0.0, 0.0]), static=True)
    rec.set_time(TIMELINE, sequence=0)
    log_path(rec, f"{root}/desired", result["desired"], color=DESIRED_COLOR, radius=0.0008)  # wider: seen around
    log_path(rec, f"{root}/actual", result["actual"], color=ACTUAL_COLOR, radius=0.0003)     # the actual path
    front = [[0.5 * (lo + hi) for lo, hi in zip(result["desired"].min(0), result["desired"].max(0), strict=True)]]
    front[0][1] = float(result["desired"][:, 1].min()) - 0.15 * robot.spec.total_length   # in front of the path
    rec.log(f"{root}/title", rr.Points3D(front, labels=[title], show_labels=True, radii=0.0002,
                                         colors=DESIRED_COLOR), static=True)
    feats = torch.from_numpy(result["features"])
    for k in range(0, len(feats), every):
        rec.set_time(TIMELINE, sequence=k)
        pose = robot.pose(feats[k])
        log_scene(rec, f"{root}/robot", {"backbone": backbone_points(robot.spec, feats[k])[None],
                                         "pose_true": pose[None]}, axis_length=0.01)
        rec.log(f"{root}/target", rr.Points3D(result["desired"][k:k + 1], colors=DESIRED_COLOR, radii=0.0015))
    err_mm = 1e3 * np.linalg.norm(result["actual"] - result["desired"], axis=-1)
    rms_mm = float(np.sqrt(np.mean(err_mm**2)))
    label = f"|actual − reference| (RMS {rms_mm:.4f} mm, max {err_mm.max():.4f} mm)"
    rec.log(f"metrics/{name}/tracking_error_mm", rr.SeriesLines(names=[label], colors=[ACTUAL_COLOR]), static=True)
    rec.send_columns(f"metrics/{name}/tracking_error_mm",
                     indexes=[rr.TimeColumn(TIMELINE, sequence=np.arange(len(err_mm)))],
                     columns=rr.Scalars.columns(scalars=err_mm))


def tracking_blueprint(results: Mapping[str, Mapping[str, float]], length: float) -> rrb.Blueprint:
    """Layout of track.rrd; ``results``: trajectory name -> its :func:`errors` (``rms_mm``, ``max_mm``).

    Left, the 3D scene: every trajectory's reference and actual tip paths and the robot at the
    time cursor (trajectory ``i`` is shifted by ``i * SCENE_SPACING`` in x; the camera sees them
    all for a robot of ``length`` [m]). Right, one plot per trajectory, titled with its name, RMS
    and max error: every step, y from 0. The time panel opens at the last step.
    """
    centre = 0.5 * SCENE_SPACING * (len(results) - 1)
    eye = rrb.EyeControls3D(position=[centre, -0.6 * SCENE_SPACING - 1.0 * length, 1.6 * length],
                            look_target=[centre, 0.0, 0.55 * length], eye_up=[0.0, 0.0, 1.0])
    titles = " and ".join(TRAJECTORIES.get(n, n) for n in results)
    scene = rrb.Spatial3DView(origin="scene", eye_controls=eye,
                              name=f"{titles}: reference (blue) vs actual tip path (orange), robot at the cursor")
    plots = [full_range_plot(TIMELINE, origin=f"metrics/{n}", from_zero=True, legend=None,
                             axis_y=rrb.ScalarAxis(range=(0.0, 1.1 * r["max_mm"] or 1.0)),
                             name=f"{TRAJECTORIES.get(n, n)}: tracking error [mm] "
                                  f"(RMS {r['rms_mm']:.4f}, max {r['max_mm']:.4f})")
             for n, r in results.items()]
    return rrb.Blueprint(rrb.Horizontal(scene, rrb.Vertical(*plots), column_shares=[3, 2]),
                         time_panel_at_end(TIMELINE), collapse_panels=True)


def write_recording(path: Path, robot: SimulatedRobot, results: Mapping[str, dict], every: int) -> None:
    """``path`` (.rrd): :func:`log_result` of every trajectory (name -> :func:`run_scenario`'s arrays),
    with :func:`tracking_blueprint` as its layout."""
    length = robot.spec.total_length
    layout = tracking_blueprint({n: errors(r, length) for n, r in results.items()}, length)
    rec = rr.RecordingStream("dacr_track_trajectory")
    rec.set_sinks(rr.FileSink(str(path)), default_blueprint=layout)
    rec.log("scene", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for i, (name, result) in enumerate(results.items()):
        log_result(rec, name, SCENE_SPACING * i, robot, result, every=every)
    rec.disconnect()


def resolve_checkpoint(ckpt: str | None, no_train: bool) -> Path:
    """--ckpt (a checkpoint or a run folder), else the newest run of runs/fk_type1, else a quickly trained
    small model."""
    if ckpt:
        return find_checkpoint(ckpt)
    try:
        found = find_checkpoint(DEFAULT_RUN)
        print(f"using {found.relative_to(ROOT)}")
        return found
    except FileNotFoundError:
        pass
    if no_train:
        sys.exit(f"no checkpoint: train one with `{' '.join(TRAIN_COMMAND)}` "
                 f"and pass --ckpt {DEFAULT_RUN.relative_to(ROOT)}")
    quick = TRAIN_COMMAND + ["--run_name", "fk_type1_quick", "--trainer.max_epochs", "4", "--data.n_train", "10000"]
    print(f"no checkpoint given: training a quick small model ({' '.join(quick)}); "
          f"for the full one run `{' '.join(TRAIN_COMMAND)}`", flush=True)
    subprocess.run([sys.executable, *quick[1:]], cwd=ROOT, check=True)
    return find_checkpoint(ROOT / "runs" / "fk_type1_quick")


def learned_jacobian(ckpt: Path, out: Path, aoti: bool) -> dexport.ExportedModule:
    """Export ``ckpt`` to ``out`` (re-used when it is already the export of this checkpoint) and load its Jacobian."""
    kind = "aoti" if aoti else "export"
    try:
        files = dexport.read_metadata(out)["modules"]["jacobian"]["files"]
        if kind in files:
            return dexport.load(out / files[kind]["file"], checkpoint=ckpt)
    except (FileNotFoundError, ValueError, KeyError):
        pass
    print(f"exporting {ckpt} → {out}/ ({'with' if aoti else 'without'} AOTInductor)", flush=True)
    dexport.export_checkpoint(ckpt, out, aoti=("jacobian",) if aoti else False)
    return dexport.load(out, "jacobian", checkpoint=ckpt)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", help="FK checkpoint of configs/robots/type1.yaml (or another robot)")
    p.add_argument("--no-train", action="store_true", help="without --ckpt: do not train, print the command")
    p.add_argument("--jacobian", choices=["learned", "analytic"], default="learned",
                   help="learned (exported) Jacobian, or the analytic CC one as a reference (slow)")
    p.add_argument("--aoti", action="store_true", help="build and use the Jacobian's AOTInductor package "
                   "(~1 min build, ~20x faster calls than the torch.export program)")
    p.add_argument("--joint-noise", type=float, default=0.0, help="std of Gaussian noise on executed joint lengths [m]")
    p.add_argument("--radius-scale", type=float, default=1.0, help="real joint radius / model radius")
    p.add_argument("--length-scale", type=float, default=1.0, help="real backbone length / model length")
    p.add_argument("--rate", type=float, default=500.0, help="control rate [Hz]")
    p.add_argument("--period", type=float, default=4.0, help="time for one lap [s]")
    p.add_argument("--laps", type=int, default=2)
    p.add_argument("--gain", type=float, default=0.5)
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "track",
                   help="export, track.rrd and summary.json go here")
    p.add_argument("--json", action="store_true", help="also print the summary as one JSON line")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(1)
    ckpt = resolve_checkpoint(args.ckpt, args.no_train)
    if args.jacobian == "learned":
        jac = learned_jacobian(ckpt, args.out / "export", args.aoti)
        spec = RobotSpec.from_dict(jac.metadata["robot"])
    else:
        spec = load_checkpoint_model(ckpt)[1].spec
        jac = analytic_jacobian(spec)
    ctrl = ResolvedRateController(spec, jac, ControllerConfig(gain=args.gain))
    robot = SimulatedRobot(spec, args.radius_scale, args.length_scale, args.joint_noise)
    period, settle = round(args.period * args.rate), round(0.5 * args.rate)
    summary = {"checkpoint": str(ckpt), "robot": spec.name, "jacobian": args.jacobian,
               "kind": getattr(jac, "kind", "analytic"), "rate_hz": args.rate, "period_s": args.period,
               "laps": args.laps, "joint_noise_m": args.joint_noise, "radius_scale": args.radius_scale,
               "length_scale": args.length_scale, "controller": dataclasses.asdict(ctrl.config), "results": {}}
    results = {}
    for kind in TRAJECTORIES:
        results[kind] = run_scenario(ctrl, robot, trajectory(kind, spec, args.laps * period, period), settle)
        summary["results"][kind] = errors(results[kind], spec.total_length)
    args.out.mkdir(parents=True, exist_ok=True)
    write_recording(args.out / "track.rrd", robot, results, every=max(1, round(args.rate / 50)))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print_summary(summary, spec, args.out)
    if args.json:
        print(json.dumps(summary))
    return summary


def print_summary(summary: dict, spec: RobotSpec, out: Path) -> None:
    print(f"\ntracking with the {summary['jacobian']} Jacobian ({summary['kind']}), robot {spec.name} "
          f"(L = {1e3 * spec.total_length:.0f} mm), {summary['rate_hz']:.0f} Hz, joint noise "
          f"{1e6 * summary['joint_noise_m']:.0f} µm, radius ×{summary['radius_scale']}, "
          f"length ×{summary['length_scale']}")
    print(f"  {'trajectory':<10} {'RMS mm':>8} {'max mm':>8} {'RMS %L':>7} {'max %L':>7} {'step p50 µs':>12}")
    for kind, r in summary["results"].items():
        print(f"  {kind:<10} {r['rms_mm']:>8.4f} {r['max_mm']:>8.4f} {r['rms_pct']:>7.4f} {r['max_pct']:>7.4f} "
              f"{r['step_p50_us']:>12.0f}")
    print(f"  Rerun: .venv/bin/rerun {out / 'track.rrd'}   summary: {out / 'summary.json'}")


if __name__ == "__main__":
    main()
