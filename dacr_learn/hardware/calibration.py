"""Calibration from single-tendon pulls: servo → (segment, joint), sign, zero, joint offsets.

Input: a recording in which one tendon at a time is pulled while the other servos are parked at a
slack level (:mod:`dacr_learn.hardware.recording`); pattern labels are *not* used. The method (slack
level and single pulls, rest tip, per-servo sign/direction/gain/taut onset from a line fit, the partition
into segments, the joint slots and offsets) is described in docs/hardware.md ("Calibration from the
single-tendon pulls"). The taut onset is reported, not applied (servo zero = 0; the CC model fits a
pretension instead).

The result is a calibrated robot YAML (offsets) and a :class:`ServoMap` YAML, with the fit quality
(angle residuals, gains) reported.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..kinematics import forward_kinematics
from ..robot import RobotSpec
from .recording import Recording
from .servo_map import ServoAssignment, ServoMap
from .slack import SlackAwareEncoder

SIGMA_ANGLE = math.radians(10.0)
SIGMA_LOG_GAIN = 0.1
ORDER_PENALTY = 1e3


@dataclass(frozen=True)
class PullFit:
    """Single-pull line fit of one servo. Angles [rad], zero [m], rms [m], gain [m/m]."""

    servo: str
    rows: int
    sign: int
    direction: float
    gain: float
    zero: float
    rms: float


def wrap(a):
    """Wrap angles to (−π, π]."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def slack_level(rec: Recording) -> float:
    """The value idle servos are parked at [m]: the median of all servo values."""
    return float(rec.servo.median())


def single_pull_rows(rec: Recording, level: float) -> list[np.ndarray]:
    """Row indices where servo column s is the only one away from the slack level, per s."""
    dev = (rec.servo - level).abs().numpy()
    thr = 0.5 * np.quantile(dev.max(1), 0.95)
    active = dev > thr
    single = active.sum(1) == 1
    return [np.nonzero(single & active[:, s])[0] for s in range(dev.shape[1])]


def rest_position(rec: Recording, rows: list[np.ndarray], level: float) -> np.ndarray:
    """Median over servos of the tip at the row where that servo is pulled least. (3,) [m]."""
    dev = (rec.servo - level).abs().numpy()
    tips = [rec.tip[idx[np.argmin(dev[idx, s])]].numpy() for s, idx in enumerate(rows) if len(idx)]
    return np.median(np.stack(tips), axis=0)


def fit_pull(rec: Recording, s: int, idx: np.ndarray, rest: np.ndarray) -> PullFit:
    """Line fit of servo column s over its single-pull rows (docs/hardware.md, calibration step 2)."""
    if len(idx) < 3:
        raise ValueError(f"{rec.source}: servo {rec.servo_ids[s]} has {len(idx)} single-pull rows, need >= 3")
    v = rec.servo[idx, s].numpy()
    p = rec.tip[idx, :2].numpy()
    dist = np.linalg.norm(p - rest[:2], axis=1)
    sign = 1 if np.corrcoef(v, dist)[0, 1] >= 0 else -1
    far = dist >= 0.25 * dist.max()
    if far.sum() < 2 or np.ptp(v[far]) == 0:
        raise ValueError(f"{rec.source}: servo {rec.servo_ids[s]}: the tip does not follow the pull")
    u = sign * v[far]
    design = np.stack([np.ones_like(u), u], 1)
    coef, *_ = np.linalg.lstsq(design, p[far], rcond=None)
    c, k = coef[0], coef[1]
    u0 = float((rest[:2] - c) @ k / (k @ k))
    rms = float(np.sqrt(((design @ coef - p[far]) ** 2).sum(1).mean()))
    return PullFit(rec.servo_ids[s], int(len(idx)), sign, float(math.atan2(k[1], k[0])),
                   float(np.linalg.norm(k)), sign * u0, rms)


def predicted_gains(spec: RobotSpec, pull: float = 1e-3) -> np.ndarray:
    """Tip deflection per unit pull of a segment's first tendon, others slack (nominal CC). (m,)"""
    enc = SlackAwareEncoder(spec, compliance=1e-12)
    starts = np.cumsum([0] + [s.num_joints for s in spec.segments])[:-1]
    x = torch.full((spec.num_segments, spec.num_length_joints), -0.1 * spec.total_length, dtype=torch.float64)
    x[torch.arange(spec.num_segments), torch.as_tensor(starts)] = pull
    with torch.no_grad():
        tip = forward_kinematics(spec, enc(x))[:, :2, 3]
    return (tip.norm(dim=-1) / pull).numpy()


def fit_layout(psi: np.ndarray, phi: np.ndarray) -> tuple[float, tuple[int, ...], np.ndarray]:
    """Rotation δ and slot permutation with ψ_s ≈ φ_slot(s) + δ. Returns (δ, slots, residuals)."""
    if len(phi) > 7:
        raise ValueError(f"joint layout with {len(phi)} joints: the permutation search supports <= 7")
    best = None
    for perm in itertools.permutations(range(len(phi)), len(psi)):
        diff = psi - phi[list(perm)]
        delta = math.atan2(np.sin(diff).mean(), np.cos(diff).mean())
        res = wrap(diff - delta)
        cost = float((res**2).sum())
        if best is None or cost < best[0]:
            best = (cost, delta, perm, res)
    return best[1], best[2], best[3]


def _layout(seg) -> np.ndarray:
    """Joint angles of a segment relative to its first joint [rad]."""
    return np.asarray(seg.joint_angles) - seg.joint_angles[0]


def partition_score(groups, psi, log_gain, layouts, log_pred) -> float:
    """Objective of the partition into segments (docs/hardware.md, calibration step 3); groups: columns per segment."""
    score, means = 0.0, []
    for g, phi in zip(groups, layouts, strict=True):
        res = fit_layout(psi[g], phi)[2]
        score += float((res**2).sum()) / SIGMA_ANGLE**2
        lg = log_gain[g]
        score += float(((lg - lg.mean()) ** 2).sum()) / SIGMA_LOG_GAIN**2
        means.append(lg.mean())
    for j, k in itertools.combinations(range(len(groups)), 2):
        if (log_pred[j] - log_pred[k]) * (means[j] - means[k]) < 0:
            score += ORDER_PENALTY
    return score


def _local_search(groups, score_fn):
    groups = [list(g) for g in groups]
    best = score_fn(groups)
    improved = True
    while improved:
        improved = False
        for j, k in itertools.combinations(range(len(groups)), 2):
            for a, b in itertools.product(range(len(groups[j])), range(len(groups[k]))):
                trial = [list(g) for g in groups]
                trial[j][a], trial[k][b] = groups[k][b], groups[j][a]
                s = score_fn(trial)
                if s < best - 1e-12:
                    groups, best, improved = trial, s, True
    return groups, best


def assign_segments(spec: RobotSpec, fits: list[PullFit], restarts: int = 20) -> list[list[int]]:
    """Servo columns of each segment (the partition minimising :func:`partition_score`)."""
    psi = np.array([f.direction for f in fits])
    log_gain = np.log([f.gain for f in fits])
    log_pred = np.log(predicted_gains(spec))
    sizes = [s.num_joints for s in spec.segments]
    score_fn = lambda g: partition_score(g, psi, log_gain, [_layout(s) for s in spec.segments], log_pred)  # noqa: E731

    def chunk(order):
        seg_order = np.argsort(-log_pred, kind="stable")
        groups, pos = [None] * len(sizes), 0
        for j in seg_order:
            groups[j] = list(order[pos:pos + sizes[j]])
            pos += sizes[j]
        return groups

    rng = np.random.default_rng(0)
    starts = [chunk(np.argsort(-log_gain, kind="stable"))]
    starts += [chunk(rng.permutation(len(fits))) for _ in range(restarts)]
    results = [_local_search(s, score_fn) for s in starts]
    return min(results, key=lambda r: r[1])[0]


def _segment_joints(seg, group: list[int], psi: np.ndarray) -> tuple[float, dict[int, int], np.ndarray]:
    """(δ, {column: joint}, residuals) for one segment, cyclic labels fixed for symmetric layouts."""
    phi = _layout(seg)
    delta, slots, res = fit_layout(psi[group], phi)
    joint = dict(zip(group, slots, strict=True))
    if seg.symmetric:
        first = joint[min(group)]
        delta += float(phi[first])
        joint = {c: (slot - first) % seg.num_joints for c, slot in joint.items()}
    return float(wrap(delta)), joint, res


def calibrate(rec: Recording, spec: RobotSpec) -> tuple[RobotSpec, ServoMap, dict]:
    """Identify the servo map and joint offsets from single pulls. Returns (spec, map, report)."""
    if len(rec.servo_ids) != spec.num_length_joints:
        raise ValueError(f"{rec.source}: {len(rec.servo_ids)} servos but {spec.name!r} has "
                         f"{spec.num_length_joints} joints")
    level = slack_level(rec)
    rows = single_pull_rows(rec, level)
    rest = rest_position(rec, rows, level)
    fits = [fit_pull(rec, s, idx, rest) for s, idx in enumerate(rows)]
    psi = np.array([f.direction for f in fits])
    groups = assign_segments(spec, fits)
    d = spec.to_dict()
    servos, per_servo, per_segment = [], {}, []
    for j, (seg, group) in enumerate(zip(spec.segments, groups, strict=True)):
        delta, joint, res = _segment_joints(seg, group, psi)
        if seg.symmetric:
            d["segments"][j]["offset"] = delta
        else:
            d["segments"][j]["joint_angles"] = [float(wrap(a + delta)) for a in _layout(seg)]
        for c, r in zip(group, res, strict=True):
            f = fits[c]
            servos.append(ServoAssignment(f.servo, j, joint[c], f.sign, 0.0))
            per_servo[f.servo] = {"segment": j, "joint": joint[c], "sign": f.sign, "rows": f.rows,
                                  "direction_deg": round(math.degrees(f.direction), 2),
                                  "angle_residual_deg": round(math.degrees(float(r)), 2),
                                  "gain_mm_per_mm": round(f.gain, 3), "taut_onset_mm": round(f.zero * 1e3, 3),
                                  "line_rms_mm": round(f.rms * 1e3, 3)}
        per_segment.append({"offset_deg": round(math.degrees(delta), 2),
                            "angle_rms_deg": round(math.degrees(float(np.sqrt((res**2).mean()))), 2),
                            "mean_gain_mm_per_mm": round(float(np.mean([fits[c].gain for c in group])), 3)})
    servos.sort(key=lambda a: (a.segment, a.joint))
    report = {"source": rec.source, "slack_level_mm": round(level * 1e3, 3),
              "rest_tip_mm": [round(v * 1e3, 2) for v in rest.tolist()],
              "predicted_gain_ratio": [round(float(g), 3) for g in predicted_gains(spec) / predicted_gains(spec)[0]],
              "segments": per_segment, "servos": per_servo}
    smap = ServoMap(spec.name, tuple(servos), level, report)
    return RobotSpec.from_dict(d), smap, report


def write_calibration(spec: RobotSpec, smap: ServoMap, robot_path: str | Path, map_path: str | Path) -> None:
    """Write the calibrated robot YAML (with a provenance comment) and the servo map YAML."""
    import yaml

    header = (f"# Calibrated from single-tendon pulls ({smap.calibration.get('source', '?')}) by\n"
              f"# dacr_learn.hardware.calibrate; servo map: {Path(map_path).parent.name}/{Path(map_path).name}\n")
    Path(robot_path).parent.mkdir(parents=True, exist_ok=True)
    Path(map_path).parent.mkdir(parents=True, exist_ok=True)
    Path(robot_path).write_text(header + yaml.safe_dump(spec.to_dict(), sort_keys=False))
    smap.to_yaml(map_path)


def default_map_path(robot_path: str | Path) -> Path:
    """servo_maps/<robot file name> in the robot YAML's folder (a glob for robot YAMLs never meets a map)."""
    p = Path(robot_path)
    return p.parent / "servo_maps" / p.name
