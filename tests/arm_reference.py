"""Independent references for the arm + continuum robot (dacr_learn.arm): NumPy only, no dacr_learn or
pytorch-kinematics code on the geometry path.

- :class:`UrdfArm`: a URDF parsed with xml.etree, its chain from the root link to a tip link walked in NumPy
  float64 (origin: R = Rz(yaw)·Ry(pitch)·Rx(roll), revolute/continuous: Rodrigues about the unit axis,
  prismatic: a translation along it), the joints in the order met along the chain, the file's limits;
- :func:`check_solution`: a whole-body joint vector against a target: the arm's NumPy FK and URDF limits,
  the mount, and the robot's joint vector checked as in tests/test_ik.py (the encoder only proposes features,
  accepted when the geometry of docs/design.md §1 reproduces q; the classic arc FK; the robot file's limits).

Used by tests/test_arm*.py and benchmarks/arm.py.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch
from conftest import classic_forward_kinematics, reference_joint_vector

from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec


def _floats(text: str | None, default: list[float]) -> np.ndarray:
    return np.array(default if text is None else [float(v) for v in text.split()], dtype=np.float64)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
                              math.sin(yaw))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


class UrdfArm:
    """The serial chain of a URDF from its root link to ``tip``, in NumPy float64."""

    def __init__(self, urdf: str | Path, tip: str):
        text = Path(urdf).read_text() if not str(urdf).lstrip().startswith("<") else str(urdf)
        root = ET.fromstring(text)
        by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
        path, link = [], tip
        while link in by_child:
            path.append(by_child[link])
            link = by_child[link].find("parent").get("link")
        self.joints = path[::-1]                              # root → tip
        self.movable = [j for j in self.joints if j.get("type") != "fixed"]
        self.names = [j.get("name") for j in self.movable]
        lower, upper = [], []
        for j in self.movable:
            lim = j.find("limit")
            if j.get("type") == "continuous" or lim is None or lim.get("lower") is None:
                lower.append(-math.inf)
                upper.append(math.inf)
            else:
                lower.append(float(lim.get("lower")))
                upper.append(float(lim.get("upper")))
        self.lower, self.upper = np.array(lower), np.array(upper)

    def tip_pose(self, theta: np.ndarray) -> np.ndarray:
        """(4, 4) pose of the tip link for the movable joints' values θ (n,)."""
        pose, i = np.eye(4), 0
        for j in self.joints:
            o = j.find("origin")
            step = np.eye(4)
            if o is not None:
                step[:3, :3] = rpy_matrix(*_floats(o.get("rpy"), [0, 0, 0]))
                step[:3, 3] = _floats(o.get("xyz"), [0, 0, 0])
            pose = pose @ step
            kind = j.get("type")
            if kind == "fixed":
                continue
            axis = _floats(j.find("axis").get("xyz") if j.find("axis") is not None else None, [1, 0, 0])
            axis = axis / np.linalg.norm(axis)
            move = np.eye(4)
            if kind == "prismatic":
                move[:3, 3] = theta[i] * axis
            else:
                move[:3, :3] = rodrigues(axis, theta[i])
            pose = pose @ move
            i += 1
        return pose

    def inside(self, theta: np.ndarray, tol: float = 1e-12) -> bool:
        return bool(np.all(theta >= self.lower - tol) and np.all(theta <= self.upper + tol))


def rotation_angle(r: np.ndarray) -> float:
    """Angle [rad] of a rotation matrix (atan2 form, accurate near 0)."""
    return math.atan2(np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2,
                      (np.trace(r) - 1) / 2)


def robot_check(spec: RobotSpec, q: np.ndarray) -> tuple[np.ndarray, bool]:
    """(tip pose (4, 4) in the robot base, inside the robot file's limits) of one joint vector; AssertionError
    if q is not on the displacement constraint (tests/test_ik.py's independent_check)."""
    f = ClarkeEncoder(spec).to(torch.float64)(torch.from_numpy(np.ascontiguousarray(q))).numpy()
    assert np.abs(reference_joint_vector(spec, f) - q).max() < 1e-9, "q is not on the displacement constraint"
    inside = True
    for k, seg in enumerate(spec.segments):
        inside &= math.hypot(f[k, 0], f[k, 1]) / seg.radius <= seg.bend * (1 + 1e-9)
        if seg.extends:
            inside &= seg.length_range[0] - 1e-12 <= f[k, 2] <= seg.length_range[1] + 1e-12
        if seg.twists:
            inside &= seg.twist_range[0] - 1e-12 <= f[k, 3] <= seg.twist_range[1] + 1e-12
    return classic_forward_kinematics(spec, f), bool(inside)


def check_solution(arm: UrdfArm, mount: np.ndarray, spec: RobotSpec, q: np.ndarray,
                   target: np.ndarray) -> tuple[float, float, bool]:
    """(position error [m], rotation error [rad] (0 for a (3,) target), inside every limit) of one whole-body
    joint vector q (n + N,) for a target (4, 4) pose or (3,) position in the arm's base frame."""
    n = len(arm.names)
    tip_c, inside_c = robot_check(spec, q[n:])
    tip = arm.tip_pose(q[:n]) @ mount @ tip_c
    inside = arm.inside(q[:n]) and inside_c
    if target.shape == (3,):
        return float(np.linalg.norm(tip[:3, 3] - target)), 0.0, inside
    return (float(np.linalg.norm(tip[:3, 3] - target[:3, 3])), rotation_angle(tip[:3, :3] @ target[:3, :3].T),
            inside)


def random_urdf(seed: int, movable: int = 5) -> tuple[str, str]:
    """(URDF text, tip link) of a random serial arm: ``movable`` revolute / continuous / prismatic joints with
    fixed joints between some of them, random origins (xyz, rpy; some omitted), random non-unit axes (some
    omitted: the URDF default (1, 0, 0)), and a side branch that is not on the chain."""
    rng = np.random.default_rng(seed)
    links, joints, parent, k = ['<link name="base"/>'], [], "base", 0
    kinds = rng.choice(["revolute", "continuous", "prismatic"], size=movable, p=[0.6, 0.2, 0.2])
    plan = []
    for kind in kinds:
        if rng.random() < 0.3:
            plan.append("fixed")
        plan.append(str(kind))
    plan.append("fixed")
    for kind in plan:
        child = f"l{k}"
        links.append(f'<link name="{child}"/>')
        origin = "" if rng.random() < 0.15 else (
            f'<origin xyz="{" ".join(f"{v:.6f}" for v in rng.uniform(-0.3, 0.3, 3))}" '
            f'rpy="{" ".join(f"{v:.9f}" for v in rng.uniform(-math.pi, math.pi, 3))}"/>')
        axis = "" if kind == "fixed" or rng.random() < 0.15 else \
            f'<axis xyz="{" ".join(f"{v:.5f}" for v in rng.normal(size=3))}"/>'
        lo = rng.uniform(-2.5, -0.2) if kind == "revolute" else rng.uniform(-0.1, 0.0)
        hi = rng.uniform(0.2, 2.5) if kind == "revolute" else rng.uniform(0.05, 0.2)
        limit = f'<limit lower="{lo:.6f}" upper="{hi:.6f}" effort="1" velocity="1"/>' \
            if kind in ("revolute", "prismatic") else ""
        joints.append(f'<joint name="j{k}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
                      f'{origin}{axis}{limit}</joint>')
        parent, k = child, k + 1
    links.append('<link name="side"/>')
    joints.append('<joint name="side_joint" type="revolute"><parent link="l0"/><child link="side"/>'
                  '<axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')
    return f'<robot name="random_arm">{"".join(links)}{"".join(joints)}</robot>', parent
