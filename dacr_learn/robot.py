"""Robot description: a frozen, validated :class:`RobotSpec` and its YAML/dict I/O.

The schema, its defaults and the errors it raises: docs/design.md §4 (``body_radius``, the envelope a wall touches:
docs/body.md; the optional ``mechanics`` block of the Cosserat-rod model: docs/cosserat.md §1). This module does
not depend on ``torch.nn``; all geometry is kept in plain floats.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SEGMENT_TYPES = ("0", "I", "II", "III")
EXTENDING_TYPES = ("I", "III")
TWISTING_TYPES = ("II", "III")
ROUTINGS = ("independent", "coupled")
DEFAULT_BEND = math.pi / 2
DEFAULT_LENGTH_RATIO = (0.8, 1.2)
DEFAULT_TWIST = (-math.pi / 2, math.pi / 2)

_ROBOT_KEYS = {"name", "routing", "segments", "mechanics"}
_SEGMENT_KEYS = {"type", "length", "radius", "joints", "offset", "joint_angles", "joint_radii", "limits",
                 "body_radius"}
_MECHANICS_KEYS = {"youngs_modulus", "shear_modulus", "poisson_ratio", "outer_radius", "inner_radius", "density",
                   "tendon_compliance"}
# Largest accepted condition number of a segment's joint layout A ([A, 1] when it extends): the float32 encoder's
# relative error grows like cond·eps, 1e-3 at this bound (docs/design.md §1); real layouts have cond ≈ 1.4–10.
MAX_LAYOUT_CONDITION = 1e4


def _fail(field: str, value: Any, expected: str) -> None:
    raise ValueError(f"{field}: got {value!r}, expected {expected}")


def _check_keys(where: str, d: Any, allowed: set[str]) -> None:
    """ValueError unless ``d`` is a mapping whose keys are among ``allowed``."""
    if not isinstance(d, Mapping):
        _fail(where, d, "a mapping with keys " + ", ".join(sorted(allowed)))
    unknown = set(d) - allowed
    if unknown:
        _fail(where, sorted(unknown), "only keys " + ", ".join(sorted(allowed)))


def _number(field: str, value: Any, expected: str, ok=math.isfinite) -> float:
    """``value`` as a float; ValueError naming ``field`` unless it is a number (not a bool) for which ``ok`` holds."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not ok(value):
        _fail(field, value, expected)
    return float(value)


def _positive_float(field: str, value: Any) -> float:
    _number(field, value, "a number", ok=lambda v: True)
    return _number(field, value, "a finite number > 0", ok=lambda v: math.isfinite(v) and v > 0)


def _float_list(field: str, value: Any) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)):
        _fail(field, value, "a list of numbers")
    return tuple(_number(f"{field}[{i}]", v, "a finite number") for i, v in enumerate(value))


def _nonnegative_float(field: str, value: Any) -> float:
    return _number(field, value, "a finite number >= 0", ok=lambda v: math.isfinite(v) and v >= 0)


def _range(field: str, value: Any, positive: bool) -> tuple[float, float]:
    lo_hi = _float_list(field, value)
    if len(lo_hi) != 2 or not lo_hi[0] < lo_hi[1] or (positive and lo_hi[0] <= 0):
        _fail(field, value, "[low, high] with low < high" + (" and low > 0" if positive else ""))
    return lo_hi


@dataclass(frozen=True)
class SegmentSpec:
    """One segment: type, nominal length l [m], reference radius d [m] and joint layout.

    ``joint_angles`` ψ_i [rad] and ``joint_radii`` d_i [m] are always explicit here; the
    ``symmetric`` flag (with ``offset``) remembers whether the YAML used ``joints/offset``.
    ``bend`` [rad], ``length_range`` [m] and ``twist_range`` [rad] are sampling limits.
    ``envelope`` [m]: the ``body_radius`` the YAML gave, or None (see :attr:`body_radius`).
    """

    type: str
    length: float
    radius: float
    joint_angles: tuple[float, ...]
    joint_radii: tuple[float, ...]
    bend: float
    length_range: tuple[float, float] | None
    twist_range: tuple[float, float] | None
    symmetric: bool
    offset: float = 0.0
    envelope: float | None = None

    @property
    def body_radius(self) -> float:
        """Envelope radius [m] of the segment's body (its backbone swept by a ball of this radius, what a wall
        touches: spacer disks or a sheath): the robot file's ``body_radius``, by default the largest joint
        radius of the segment (the tendons run at the disks' rim)."""
        return self.envelope if self.envelope is not None else max(self.joint_radii)

    @property
    def num_joints(self) -> int:
        """n: number of displacement joints of this segment (twist not counted)."""
        return len(self.joint_angles)

    @property
    def extends(self) -> bool:
        """True when the segment length β is actuated (types I, III)."""
        return self.type in EXTENDING_TYPES

    @property
    def twists(self) -> bool:
        """True when the twist α is actuated (types II, III)."""
        return self.type in TWISTING_TYPES

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str) -> SegmentSpec:
        _check_keys(where, d, _SEGMENT_KEYS)
        seg_type = str(d.get("type", ""))
        if seg_type not in SEGMENT_TYPES:
            _fail(f"{where}.type", d.get("type"), 'one of "0", "I", "II", "III"')
        length = _positive_float(f"{where}.length", d.get("length"))
        radius = _positive_float(f"{where}.radius", d.get("radius"))
        angles, radii, symmetric, offset = _joint_layout(d, where, radius)
        bend, length_range, twist_range = _limits(d.get("limits", {}), where, seg_type, length)
        envelope = _positive_float(f"{where}.body_radius", d["body_radius"]) if "body_radius" in d else None
        seg = cls(seg_type, length, radius, angles, radii, bend, length_range, twist_range, symmetric, offset,
                  envelope)
        _check_rank(seg, where)
        return seg

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"type": self.type, "length": self.length, "radius": self.radius}
        if self.symmetric:
            d["joints"] = self.num_joints
            d["offset"] = self.offset
        else:
            d["joint_angles"] = list(self.joint_angles)
            d["joint_radii"] = list(self.joint_radii)
        limits: dict[str, Any] = {"bend": self.bend}
        if self.length_range is not None:
            limits["length"] = list(self.length_range)
        if self.twist_range is not None:
            limits["twist"] = list(self.twist_range)
        d["limits"] = limits
        if self.envelope is not None:
            d["body_radius"] = self.envelope
        return d


def _joint_layout(d: Mapping[str, Any], where: str, radius: float):
    """Return (angles, radii, symmetric, offset) from either joints/offset or joint_angles."""
    if "joint_angles" in d:
        if "joints" in d or "offset" in d:
            _fail(where, sorted(set(d) & {"joints", "offset"}), "either joints/offset or joint_angles, not both")
        angles = _float_list(f"{where}.joint_angles", d["joint_angles"])
        if len(angles) < 3:
            _fail(f"{where}.joint_angles", list(angles), "at least 3 joints")
        if "joint_radii" in d:
            radii = _float_list(f"{where}.joint_radii", d["joint_radii"])
            if len(radii) != len(angles):
                _fail(f"{where}.joint_radii", list(radii), f"{len(angles)} radii, one per joint angle")
            for i, r in enumerate(radii):
                _positive_float(f"{where}.joint_radii[{i}]", r)
        else:
            radii = (radius,) * len(angles)
        return angles, radii, False, 0.0
    if "joint_radii" in d:
        _fail(f"{where}.joint_radii", d["joint_radii"], "joint_radii only together with joint_angles")
    n = d.get("joints")
    if isinstance(n, bool) or not isinstance(n, int):
        _fail(f"{where}.joints", n, "an integer number of joints >= 3 (or joint_angles)")
    if n < 3:
        _fail(f"{where}.joints", n, "at least 3 joints")
    offset = _number(f"{where}.offset", d.get("offset", 0.0), "a finite angle in radians")
    angles = tuple(offset + 2 * math.pi * i / n for i in range(n))
    return angles, (radius,) * n, True, offset


def _limits(lim: Any, where: str, seg_type: str, length: float):
    if not isinstance(lim, Mapping):
        _fail(f"{where}.limits", lim, "a mapping with keys bend, length, twist")
    allowed = {"bend"} | ({"length"} if seg_type in EXTENDING_TYPES else set()) | (
        {"twist"} if seg_type in TWISTING_TYPES else set())
    extra = set(lim) - allowed
    if extra:
        _fail(f"{where}.limits", sorted(extra), f"only keys {sorted(allowed)} for a type-{seg_type} segment")
    bend = _number(f"{where}.limits.bend", lim.get("bend", DEFAULT_BEND), "a bending angle in (0, pi] rad",
                   ok=lambda b: 0 < b <= math.pi)
    length_range = twist_range = None
    if seg_type in EXTENDING_TYPES:
        default = [length * DEFAULT_LENGTH_RATIO[0], length * DEFAULT_LENGTH_RATIO[1]]
        length_range = _range(f"{where}.limits.length", lim.get("length", default), positive=True)
    if seg_type in TWISTING_TYPES:
        twist_range = _range(f"{where}.limits.twist", lim.get("twist", list(DEFAULT_TWIST)), positive=False)
    return bend, length_range, twist_range


def layout_condition(seg: SegmentSpec) -> float:
    """cond(A) = σ_max/σ_min of the n×2 matrix A (of [A, 1] for an extending segment); inf when rank deficient."""
    psi, r = np.array(seg.joint_angles), np.array(seg.joint_radii)
    a = (r / seg.radius)[:, None] * np.stack([np.cos(psi), np.sin(psi)], axis=1)
    if seg.extends:
        a = np.concatenate([a, np.ones((len(psi), 1))], axis=1)
    s = np.linalg.svd(a, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def _check_rank(seg: SegmentSpec, where: str) -> None:
    """A (and [A, 1] for extending segments) must have full column rank, numerically: cond ≤ MAX_LAYOUT_CONDITION."""
    cond = layout_condition(seg)
    if not cond <= MAX_LAYOUT_CONDITION:
        field = f"{where}.joint_angles" if not seg.symmetric else f"{where}.joints"
        what = "[A, 1]" if seg.extends else "A"
        raise ValueError(f"{field}: got {list(seg.joint_angles)}, expected a joint layout whose matrix {what} "
                         f"has full column rank with condition number <= {MAX_LAYOUT_CONDITION:.0e} (joints "
                         f"spread around the backbone, not all on one line), found cond({what}) = {cond:.3g}")
    if seg.twists and len(set(seg.joint_radii)) > 1:
        _fail(f"{where}.joint_radii", list(seg.joint_radii), "equal radii for a twisting segment (type II/III)")


@dataclass(frozen=True)
class MechanicsSpec:
    """Backbone material and cross-section (one rod through all segments) and tendon compliance.

    E, G [Pa]; radii [m]; density [kg/m³]; tendon_compliance 1/(E_t·A_t) [1/N]. ``poisson_ratio``
    remembers which of ν / G the YAML gave (None: G given), so :meth:`to_dict` writes it back.
    """

    youngs_modulus: float
    shear_modulus: float
    outer_radius: float
    inner_radius: float = 0.0
    density: float = 0.0
    tendon_compliance: float = 0.0
    poisson_ratio: float | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "mechanics") -> MechanicsSpec:
        _check_keys(where, d, _MECHANICS_KEYS)
        e = _positive_float(f"{where}.youngs_modulus", d.get("youngs_modulus"))
        if ("shear_modulus" in d) == ("poisson_ratio" in d):
            _fail(where, sorted(set(d) & {"shear_modulus", "poisson_ratio"}),
                  "exactly one of shear_modulus [Pa] and poisson_ratio")
        nu = d.get("poisson_ratio")
        if "poisson_ratio" in d:
            nu = _number(f"{where}.poisson_ratio", nu, "a number in (-1, 0.5]", ok=lambda v: -1 < v <= 0.5)
        g = e / (2 * (1 + nu)) if nu is not None else _positive_float(f"{where}.shear_modulus", d["shear_modulus"])
        outer = _positive_float(f"{where}.outer_radius", d.get("outer_radius"))
        inner = _nonnegative_float(f"{where}.inner_radius", d.get("inner_radius", 0.0))
        if inner >= outer:
            _fail(f"{where}.inner_radius", inner, f"a radius < outer_radius = {outer} m")
        return cls(e, g, outer, inner, _nonnegative_float(f"{where}.density", d.get("density", 0.0)),
                   _nonnegative_float(f"{where}.tendon_compliance", d.get("tendon_compliance", 0.0)), nu)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"youngs_modulus": self.youngs_modulus}
        d.update({"shear_modulus": self.shear_modulus} if self.poisson_ratio is None
                 else {"poisson_ratio": self.poisson_ratio})
        return d | {"outer_radius": self.outer_radius, "inner_radius": self.inner_radius, "density": self.density,
                    "tendon_compliance": self.tendon_compliance}


@dataclass(frozen=True)
class RobotSpec:
    """A chain of segments with a routing mode. Construct with :meth:`from_dict`/:meth:`from_yaml`.

    ``mechanics`` (optional, None when the YAML has no ``mechanics:`` block) parameterises the
    Cosserat-rod model; the kinematic code ignores it.
    """

    name: str
    routing: str
    segments: tuple[SegmentSpec, ...]
    mechanics: MechanicsSpec | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotSpec:
        _check_keys("robot", d, _ROBOT_KEYS)
        name = d.get("name", "robot")
        if not isinstance(name, str) or not name:
            _fail("name", name, "a non-empty string")
        routing = d.get("routing", "independent")
        if routing not in ROUTINGS:
            _fail("routing", routing, "'independent' or 'coupled'")
        segs = d.get("segments")
        if not isinstance(segs, (list, tuple)) or not segs:
            _fail("segments", segs, "a non-empty list of segments")
        segments = tuple(SegmentSpec.from_dict(s, f"segments[{j}]") for j, s in enumerate(segs))
        if routing == "coupled":
            for j, seg in enumerate(segments[:-1]):
                if seg.twists:
                    _fail(f"segments[{j}].type", seg.type, "a non-twisting segment: coupled routing through a "
                          "twisting segment (type II/III) is not modelled")
        mechanics = MechanicsSpec.from_dict(d["mechanics"]) if "mechanics" in d else None
        return cls(name, routing, segments, mechanics)

    @classmethod
    def from_yaml(cls, path: str | Path) -> RobotSpec:
        """Read a robot YAML file; every ValueError names the file (and the field, see :meth:`from_dict`)."""
        from .checks import prefix_errors, read_yaml  # imports torch, which the rest of this module does not need

        d = read_yaml(path, "a robot description in YAML (see configs/robots/)")
        if d is None:
            raise ValueError(f"{path}: expected a robot description in YAML (see configs/robots/), "
                             "found an empty file (no YAML content)")
        return prefix_errors(path, cls.from_dict, d)

    @classmethod
    def coerce(cls, robot: str | Path | Mapping[str, Any] | RobotSpec) -> RobotSpec:
        """A RobotSpec from a RobotSpec (returned as is), a description dict or the path of a robot YAML."""
        if isinstance(robot, RobotSpec):
            return robot
        if isinstance(robot, Mapping):
            return cls.from_dict(robot)
        if isinstance(robot, (str, Path)):
            return cls.from_yaml(robot)
        _fail("robot", robot, "a RobotSpec, a robot description dict or the path of a robot YAML file")

    def to_dict(self) -> dict[str, Any]:
        d = {"name": self.name, "routing": self.routing, "segments": [s.to_dict() for s in self.segments]}
        return d if self.mechanics is None else d | {"mechanics": self.mechanics.to_dict()}

    def to_yaml(self, path: str | Path) -> None:
        import yaml

        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))

    @property
    def num_segments(self) -> int:
        """m: number of segments."""
        return len(self.segments)

    @property
    def num_length_joints(self) -> int:
        """Number of joint lengths in the joint vector (all segments' joints)."""
        return sum(s.num_joints for s in self.segments)

    @property
    def num_joints(self) -> int:
        """Length of the joint vector: joint lengths, then one α per twisting segment."""
        return self.num_length_joints + sum(s.twists for s in self.segments)

    @property
    def total_length(self) -> float:
        """Sum of nominal segment lengths l [m] (the scale of error percentages)."""
        return sum(s.length for s in self.segments)

    @property
    def num_actuated_features(self) -> int:
        """Number of free feature columns: 2 per segment + β and α where actuated."""
        return sum(2 + s.extends + s.twists for s in self.segments)
