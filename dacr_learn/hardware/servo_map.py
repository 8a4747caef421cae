"""Servo map: which servo column drives which joint of which segment, with sign and zero.

YAML (SI units, written by :mod:`dacr_learn.hardware.calibration`; its keys: docs/hardware.md, "The recordings",
*Servo maps*): ``robot``, ``slack_level`` [m], ``servos`` (one ``{servo, segment, joint, sign, zero}`` per servo
column, any order), an informational ``calibration`` block ignored on load. Joint displacement (the DACR ρ_i of that
joint, positive = tendon shortened): ``x = sign · (servo_value − zero)`` [m]; ``segment`` and ``joint`` index the
RobotSpec (0-based, joints in the order of the segment's joint angles).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..checks import prefix_errors, read_yaml
from ..robot import RobotSpec
from .recording import Recording

_KEYS = {"robot", "slack_level", "servos", "calibration"}
_SERVO_KEYS = {"servo", "segment", "joint", "sign", "zero"}


@dataclass(frozen=True)
class ServoAssignment:
    """servo id → (segment, joint); sign ±1 (+1: larger value = pulled); zero [m]."""

    servo: str
    segment: int
    joint: int
    sign: int = 1
    zero: float = 0.0


def _number(value: Any, kind: type, field_name: str):
    """``kind(value)`` for an int or float field; ValueError naming the field otherwise (bools refused)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        ok = ok and float(value).is_integer()
    if not ok:
        raise ValueError(f"servo map.{field_name}: expected {'an integer' if kind is int else 'a number'}, "
                         f"got {value!r:.100}")
    return kind(value)


@dataclass(frozen=True)
class ServoMap:
    """All servo assignments of a robot plus the slack level [m]."""

    robot: str
    servos: tuple[ServoAssignment, ...]
    slack_level: float
    calibration: dict[str, Any] = field(default_factory=dict, compare=False)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ServoMap:
        if not isinstance(d, Mapping) or set(d) - _KEYS:
            raise ValueError(f"servo map: expected a mapping with keys {sorted(_KEYS)}, got {d!r:.200}")
        entries = d.get("servos")
        if not isinstance(entries, list) or not entries:
            raise ValueError(f"servo map.servos: expected a non-empty list, got {entries!r:.200}")
        servos = []
        for k, e in enumerate(entries):
            if not isinstance(e, Mapping) or set(e) - _SERVO_KEYS or not {"servo", "segment", "joint"} <= set(e):
                raise ValueError(f"servo map.servos[{k}]: expected keys servo, segment, joint[, sign, zero], got {e!r}")
            sign = _number(e.get("sign", 1), int, f"servos[{k}].sign")
            if sign not in (1, -1):
                raise ValueError(f"servo map.servos[{k}].sign: got {sign}, expected 1 or -1")
            servos.append(ServoAssignment(str(e["servo"]), _number(e["segment"], int, f"servos[{k}].segment"),
                                          _number(e["joint"], int, f"servos[{k}].joint"), sign,
                                          _number(e.get("zero", 0.0), float, f"servos[{k}].zero")))
        calibration = d.get("calibration", {}) or {}
        if not isinstance(calibration, Mapping):
            raise ValueError(f"servo map.calibration: expected a mapping, got {calibration!r:.200}")
        return cls(str(d.get("robot", "robot")), tuple(servos),
                   _number(d.get("slack_level", 0.0), float, "slack_level"), dict(calibration))

    @classmethod
    def from_yaml(cls, path: str | Path) -> ServoMap:
        return prefix_errors(path, cls.from_dict, read_yaml(path, "a servo map YAML (robot, slack_level, servos)"))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"robot": self.robot, "slack_level": self.slack_level,
                             "servos": [{"servo": s.servo, "segment": s.segment, "joint": s.joint,
                                         "sign": s.sign, "zero": s.zero} for s in self.servos]}
        if self.calibration:
            d["calibration"] = self.calibration
        return d

    def to_yaml(self, path: str | Path) -> None:
        import yaml

        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False, width=110))

    def check(self, spec: RobotSpec, servo_ids: tuple[str, ...] | None = None) -> None:
        """ValueError unless every joint of ``spec`` has exactly one servo (and the ids match)."""
        slots = {(j, i) for j, seg in enumerate(spec.segments) for i in range(seg.num_joints)}
        got = [(s.segment, s.joint) for s in self.servos]
        if sorted(got) != sorted(slots):
            missing, extra = sorted(slots - set(got)), sorted(set(got) - slots)
            raise ValueError(f"servo map for {spec.name!r}: (segment, joint) slots missing {missing}, "
                             f"unknown or repeated {extra or [g for g in got if got.count(g) > 1]}")
        if servo_ids is not None and sorted(s.servo for s in self.servos) != sorted(servo_ids):
            raise ValueError(f"servo map ids {sorted(s.servo for s in self.servos)} do not match the "
                             f"recording's servo columns {sorted(servo_ids)}")

    def column_order(self, spec: RobotSpec, servo_ids: tuple[str, ...]) -> list[int]:
        """For each joint in spec order (segment 1 joints, segment 2 joints, ...): its column index."""
        self.check(spec, servo_ids)
        by_slot = {(s.segment, s.joint): servo_ids.index(s.servo) for s in self.servos}
        return [by_slot[(j, i)] for j, seg in enumerate(spec.segments) for i in range(seg.num_joints)]

    def _sign_zero(self, spec: RobotSpec, like: Tensor) -> tuple[Tensor, Tensor]:
        by_slot = {(s.segment, s.joint): s for s in self.servos}
        order = [by_slot[(j, i)] for j, seg in enumerate(spec.segments) for i in range(seg.num_joints)]
        sign = torch.tensor([s.sign for s in order], dtype=like.dtype, device=like.device)
        zero = torch.tensor([s.zero for s in order], dtype=like.dtype, device=like.device)
        return sign, zero

    def displacements(self, spec: RobotSpec, rec: Recording) -> Tensor:
        """Joint displacements (N, num_length_joints) [m] in spec order of a recording's servo values."""
        return self.command_displacements(spec, rec.servo_ids, rec.servo)

    def command_displacements(self, spec: RobotSpec, servo_ids: tuple[str, ...], servo: Tensor) -> Tensor:
        """Joint displacements (..., num_length_joints) [m] in spec order of servo values (..., S) [m] in
        ``servo_ids`` column order: sign·(value − zero)."""
        cols = self.column_order(spec, tuple(servo_ids))
        sign, zero = self._sign_zero(spec, servo)
        return sign * (servo[..., cols] - zero)

    def servo_values(self, spec: RobotSpec, servo_ids: tuple[str, ...], x: Tensor) -> Tensor:
        """Inverse of :meth:`displacements`: joint displacements (..., N) → servo values in column order."""
        cols = self.column_order(spec, servo_ids)
        sign, zero = self._sign_zero(spec, x)
        values = x * sign + zero
        out = torch.empty_like(values)
        out[..., cols] = values
        return out
