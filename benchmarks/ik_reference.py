"""An independent check of IK solutions, in NumPy, sharing no code with dacr_learn's solver or kinematics.

From a robot's YAML numbers only: the joint-length geometry of docs/design.md §1 (a joint of segment j at radius
d_i and angle ψ_i runs along every segment k it passes and collects √((α_k d_i)² + β_k²) − (d_i/d_k)(ρ_re cos ψ_i +
ρ_im sin ψ_i)), inverted by least squares for the features of a joint vector; the classic Webster & Jones arc
Rz(α)·Rz(θ)Ry(φ)Rz(−θ) for the tip; the limits of the file. A solution passes when its joints lie on the
displacement constraint (the features rebuild them to ``constraint_tol``), its features are inside the limits and
its tip is within the tolerance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml


@dataclass
class Segment:
    type: str
    length: float
    radius: float
    angles: np.ndarray
    radii: np.ndarray
    bend: float
    length_range: tuple[float, float] | None
    twist_range: tuple[float, float] | None

    @property
    def extends(self) -> bool:
        return self.type in ("I", "III")

    @property
    def twists(self) -> bool:
        return self.type in ("II", "III")


def read_robot(path: str | Path) -> tuple[list[Segment], str]:
    """(segments, routing) of a robot YAML file (docs/design.md §4), read with PyYAML only."""
    d = yaml.safe_load(Path(path).read_text())
    segs = []
    for s in d["segments"]:
        n = s.get("joints")
        angles = (np.asarray(s["joint_angles"], float) if "joint_angles" in s
                  else s.get("offset", 0.0) + 2 * math.pi * np.arange(n) / n)
        radii = np.asarray(s.get("joint_radii", [s["radius"]] * len(angles)), float)
        lim = s.get("limits", {})
        t = str(s["type"])
        length_range = tuple(lim.get("length", (0.8 * s["length"], 1.2 * s["length"]))) if t in ("I", "III") else None
        twist_range = tuple(lim.get("twist", (-math.pi / 2, math.pi / 2))) if t in ("II", "III") else None
        bend = float(lim.get("bend", math.pi / 2))
        segs.append(Segment(t, float(s["length"]), float(s["radius"]), angles, radii, bend, length_range, twist_range))
    return segs, d.get("routing", "independent")


def _joints(segs, routing):
    """(segment j, angle, radius, the segments it passes) of every length joint."""
    out = []
    for j, s in enumerate(segs):
        passed = list(range(j + 1)) if routing == "coupled" else [j]
        out += [(j, a, r, passed) for a, r in zip(s.angles, s.radii, strict=True)]
    return out


def joint_vector(segs, routing, f: np.ndarray) -> np.ndarray:
    """Joint vectors (n, N) of features f (n, m, 4) (ρ_re, ρ_im, β, α)."""
    cols = []
    for _, psi, di, passed in _joints(segs, routing):
        total = 0.0
        for k in passed:
            s = segs[k]
            beta = f[:, k, 2] if s.extends else s.length
            alpha = f[:, k, 3] if s.twists else 0.0
            total = total + np.sqrt((alpha * di) ** 2 + beta**2) - di / s.radius * (
                f[:, k, 0] * math.cos(psi) + f[:, k, 1] * math.sin(psi))
        cols.append(total)
    cols += [f[:, k, 3] for k, s in enumerate(segs) if s.twists]
    return np.stack(cols, axis=-1)


def features(segs, routing, q: np.ndarray) -> np.ndarray:
    """Least-squares features (n, m, 4) of joint vectors q (n, N): ρ of every segment and the helix length h of each
    extending one solve q_len − (known helix lengths) = A·w; β = h (type I) or √(h² − (α d)²) (type III)."""
    m, n = len(segs), q.shape[0]
    joints = _joints(segs, routing)
    alpha = np.zeros((n, m))
    tw = [k for k, s in enumerate(segs) if s.twists]
    alpha[:, tw] = q[:, len(joints):]
    ext = [k for k, s in enumerate(segs) if s.extends]
    a = np.zeros((len(joints), 2 * m + len(ext)))
    known = np.zeros((n, len(joints)))
    for i, (_, psi, di, passed) in enumerate(joints):
        for k in passed:
            s = segs[k]
            a[i, 2 * k:2 * k + 2] = [-di / s.radius * math.cos(psi), -di / s.radius * math.sin(psi)]
            if s.extends:
                a[i, 2 * m + ext.index(k)] = 1.0
            else:
                known[:, i] += np.sqrt((alpha[:, k] * di) ** 2 + s.length**2)
    w = np.linalg.lstsq(a, (q[:, :len(joints)] - known).T, rcond=None)[0].T
    f = np.zeros((n, m, 4))
    f[:, :, :2] = w[:, :2 * m].reshape(n, m, 2)
    for k, s in enumerate(segs):
        f[:, k, 2] = s.length
        if s.extends:
            h = w[:, 2 * m + ext.index(k)]
            f[:, k, 2] = np.sqrt(np.maximum(h**2 - (alpha[:, k] * s.radii[0]) ** 2, 0.0)) if s.twists else h
    f[:, :, 3] = alpha
    return f


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def tip_poses(segs, f: np.ndarray) -> np.ndarray:
    """Tip poses (n, 4, 4) of features f (n, m, 4): the product of Rz(α)·arc(θ, φ, β) per segment."""
    n = f.shape[0]
    tip = np.tile(np.eye(4), (n, 1, 1))
    for k, s in enumerate(segs):
        phi = np.hypot(f[:, k, 0], f[:, k, 1]) / s.radius
        theta = np.arctan2(f[:, k, 1], f[:, k, 0])
        beta = f[:, k, 2] if s.extends else np.full(n, s.length)
        alpha = f[:, k, 3] if s.twists else np.zeros(n)
        t = np.tile(np.eye(4), (n, 1, 1))
        t[:, :3, :3] = _rz(alpha) @ _rz(theta) @ _ry(phi) @ _rz(-theta)
        chord_dir = np.where(phi > 0, beta / np.where(phi > 0, phi, 1.0), 0.0)
        one_minus_cos = 2 * np.sin(phi / 2) ** 2
        p = np.stack([np.cos(theta) * one_minus_cos * chord_dir, np.sin(theta) * one_minus_cos * chord_dir,
                      np.where(phi > 0, np.sin(phi) * chord_dir, beta)], -1)
        t[:, :3, 3] = (_rz(alpha) @ p[..., None])[..., 0]
        tip = tip @ t
    return tip


def inside(segs, f: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    ok = np.ones(f.shape[0], dtype=bool)
    for k, s in enumerate(segs):
        ok &= np.hypot(f[:, k, 0], f[:, k, 1]) / s.radius <= s.bend * (1 + tol)
        if s.extends:
            ok &= (f[:, k, 2] >= s.length_range[0] - tol) & (f[:, k, 2] <= s.length_range[1] + tol)
        if s.twists:
            ok &= (f[:, k, 3] >= s.twist_range[0] - tol) & (f[:, k, 3] <= s.twist_range[1] + tol)
    return ok


def check(robot: str | Path, q: np.ndarray, target: np.ndarray, tolerance=(1e-6, 1e-5),
          constraint_tol: float = 1e-9) -> dict[str, np.ndarray]:
    """Independent verdicts on joint vectors q (n, N) for targets (n, 4, 4) poses or (n, 3) positions: pos_err [m],
    rot_err [rad] (0 for positions), on_constraint, inside, ok (all of them within the tolerance)."""
    segs, routing = read_robot(robot)
    f = features(segs, routing, q)
    rebuilt = joint_vector(segs, routing, f)
    on = np.abs(rebuilt - q).max(-1) <= constraint_tol
    tip = tip_poses(segs, f)
    if target.ndim == 2:
        pos_err, rot_err = np.linalg.norm(tip[:, :3, 3] - target, axis=-1), np.zeros(len(q))
    else:
        pos_err = np.linalg.norm(tip[:, :3, 3] - target[:, :3, 3], axis=-1)
        r = tip[:, :3, :3] @ np.swapaxes(target[:, :3, :3], -1, -2)
        vee = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
        rot_err = np.arctan2(np.linalg.norm(vee, axis=-1) / 2, (np.trace(r, axis1=-2, axis2=-1) - 1) / 2)
    lim = inside(segs, f)
    ok = on & lim & (pos_err <= tolerance[0]) & (rot_err <= tolerance[1])
    return {"pos_err": pos_err, "rot_err": rot_err, "on_constraint": on, "inside": lim, "ok": ok}
