"""A rigid arm from a URDF: a float64 pytorch-kinematics serial chain, its joints and their limits.

:func:`load_arm` builds the chain from the URDF's root link (or ``root``) to the ``tip`` link with
``pytorch_kinematics.build_chain_from_urdf`` / ``SerialChain``, corrected where pytorch-kinematics departs from the
file (origins in float64, the default axis (1, 0, 0)): docs/arm.md, "The URDF, exactly". The arm's joints are the
chain's movable joints in its order (``chain.get_joint_parameter_names()``): revolute [rad], prismatic [m], their
limits from the file; a ``continuous`` joint gets the box [−2π, 2π]; mimic joints are a ValueError.
"""
from __future__ import annotations

import contextlib
import io
import math
from dataclasses import dataclass
from pathlib import Path

import pytorch_kinematics as pk
import torch
from pytorch_kinematics import transforms as tf
from pytorch_kinematics.urdf_parser_py.urdf import URDF
from torch import Tensor

from ..checks import F64
from ..limits import Limits
from .geometry import LinkCapsules, link_capsules

CONTINUOUS_RANGE = 2 * math.pi   # [rad]: the box of a joint without limits is ±this


@dataclass(frozen=True)
class Arm:
    """A serial arm: ``chain`` (pytorch-kinematics SerialChain, float64), its movable ``joint_names`` (n,) in
    the chain's order, ``joint_types`` ("revolute" / "prismatic"), box ``limits`` (n variables, scale = half
    the range) of the URDF's joint limits, the ``tip`` link and ``frame_names``: the chain's frames, root to
    tip (link frames, for drawing); ``geometry``: the links' collision capsules (:mod:`.geometry`)."""

    chain: pk.SerialChain
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    limits: Limits
    tip: str
    frame_names: tuple[str, ...]
    source: str
    geometry: LinkCapsules | None = None

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def tip_pose(self, theta: Tensor) -> Tensor:
        """Tip-link pose in the arm's base frame: joint values θ (B, n) → (B, 4, 4) [m] (pytorch-kinematics FK,
        differentiable by plain autograd, also under torch.func)."""
        transforms = self.chain.forward_kinematics_tensor(theta, analytical_grad=False)
        return transforms[self.frame_index(self.tip)]

    def frames(self, theta: Tensor) -> Tensor:
        """Every frame of the chain (``frame_names`` order): θ (B, n) → (B, F, 4, 4) [m]."""
        transforms = self.chain.forward_kinematics_tensor(theta, analytical_grad=False)
        return transforms[self.chain.get_frame_indices(*self.frame_names)].transpose(0, 1)

    def frame_index(self, name: str) -> int:
        return int(self.chain.get_frame_indices(name)[0])


def _quiet(parse, text: bytes):
    """A parse by pytorch-kinematics' URDF parser, without its warnings on unknown tags (dynamics, transmissions)."""
    with contextlib.redirect_stderr(io.StringIO()):
        return parse(text)


def _exact_transform(origin) -> tf.Transform3d:
    """A URDF <origin xyz rpy> as a float64 Transform3d: R = Rz(yaw)·Ry(pitch)·Rx(roll) (fixed axes x, y, z)."""
    xyz = [0.0, 0.0, 0.0] if origin is None or origin.xyz is None else [float(v) for v in origin.xyz]
    rpy = [0.0, 0.0, 0.0] if origin is None or origin.rpy is None else [float(v) for v in origin.rpy]
    rot = tf.euler_angles_to_matrix(torch.tensor(rpy[::-1], dtype=F64), "ZYX")
    matrix = torch.eye(4, dtype=F64)
    matrix[:3, :3], matrix[:3, 3] = rot, torch.tensor(xyz, dtype=F64)
    return tf.Transform3d(matrix=matrix, dtype=F64)


def load_arm(urdf: str | Path, tip: str, root: str = "") -> Arm:
    """The arm of a URDF file (or URDF text) from ``root`` (default: the file's root link) to the ``tip`` link.

    ValueError for a file that is not a URDF, an unknown tip or root link, a chain without movable joints,
    a mimic joint, or a joint whose range is empty.
    """
    text, source = _urdf_text(urdf)
    try:
        robot = _quiet(URDF.from_xml_string, text)
    except Exception as err:                              # the parser raises assorted errors on bad XML
        raise ValueError(f"arm {source}: not a URDF file ({type(err).__name__}: {err})") from err
    links = [link.name for link in robot.links]
    for flag, name in (("--arm-tip", tip), ("root", root)):
        if name and name not in links:
            raise ValueError(f"{flag} {name!r}: no such link in {source}; its links are {links}")
    try:
        chain = _quiet(pk.build_chain_from_urdf, text).to(dtype=F64)
    except KeyError as err:                               # a joint type pytorch-kinematics has no model of
        kinds = sorted({j.type for j in robot.joints} - {"revolute", "continuous", "prismatic", "fixed"})
        raise ValueError(f"arm {source}: pytorch-kinematics cannot build this URDF (joint types {kinds or err}); "
                         f"expected revolute, continuous, prismatic and fixed joints") from err
    for joint in robot.joints:                           # the float64 geometry (pk parses it in float32)
        frame = chain.find_frame(joint.child)
        if frame is None:
            continue
        frame.joint.offset = _exact_transform(joint.origin)
        axis = torch.tensor([1.0, 0.0, 0.0] if joint.axis is None else [float(v) for v in joint.axis], dtype=F64)
        if joint.type != "fixed" and not torch.linalg.vector_norm(axis) > 0:
            raise ValueError(f"arm {source}: joint {joint.name!r} has a zero axis")
        frame.joint.axis = axis / torch.linalg.vector_norm(axis).clamp_min(1e-300)   # URDF default: (1, 0, 0)
    try:
        serial = pk.SerialChain(chain, tip, root, dtype=F64)
    except (ValueError, KeyError, IndexError) as err:
        raise ValueError(f"arm {source}: no serial chain from {root or 'the root link'} to {tip!r} ({err})") from err
    names = tuple(serial.get_joint_parameter_names())
    if not names:
        raise ValueError(f"arm {source}: the chain to {tip!r} has no movable joint")
    by_name = {j.name: j for j in robot.joints}
    mimic = [n for n in names if by_name[n].mimic is not None]
    if mimic:
        raise ValueError(f"arm {source}: mimic joints are not supported, found {mimic} on the chain to {tip!r}")
    limits, types = _joint_limits(names, by_name, source)
    frames = tuple(serial.get_frame_names(exclude_fixed=False))
    folder = Path(source).parent if source != "<URDF text>" else Path.cwd()
    return Arm(serial, names, types, limits, tip, frames, source, link_capsules(robot, serial, frames, folder))


def _urdf_text(urdf: str | Path) -> tuple[bytes, str]:
    """The URDF as bytes (the parser refuses a str with an encoding declaration) and a name for messages."""
    if isinstance(urdf, str) and urdf.lstrip().startswith("<"):
        return urdf.encode("utf-8"), "<URDF text>"
    path = Path(urdf)
    if not path.is_file():
        raise FileNotFoundError(f"--arm {urdf}: no such file; expected a URDF file")
    return path.read_bytes(), str(path)


def _joint_limits(names: tuple[str, ...], by_name: dict, source: str) -> tuple[Limits, tuple[str, ...]]:
    """Box limits of the chain's joints from the URDF (a continuous joint: ±CONTINUOUS_RANGE)."""
    lower, upper, types = [], [], []
    for n in names:
        joint = by_name[n]
        types.append("prismatic" if joint.type == "prismatic" else "revolute")
        lo, hi = (None, None) if joint.limit is None else (joint.limit.lower, joint.limit.upper)
        if joint.type == "continuous" or lo is None or hi is None or not math.isfinite(lo) or not math.isfinite(hi):
            if joint.type == "prismatic":
                raise ValueError(f"arm {source}: prismatic joint {n!r} has no finite limits")
            lo, hi = -CONTINUOUS_RANGE, CONTINUOUS_RANGE
        if not lo < hi:
            raise ValueError(f"arm {source}: joint {n!r} has an empty range [{lo}, {hi}]; make it a fixed joint")
        lower.append(float(lo))
        upper.append(float(hi))
    return Limits.boxes(lower, upper, tuple(f"arm.{n}" for n in names)), tuple(types)
