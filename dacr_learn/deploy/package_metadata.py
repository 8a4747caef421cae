"""The metadata an AOTInductor package carries inside itself, for loaders without Python (cpp/, docs/cpp.md).

``metadata.json`` next to the packages is for :func:`dacr_learn.export.load`; a C++ controller reads the package's
own metadata instead (``AOTIModelPackageLoader::get_metadata()``: a flat map string → string, written by
Inductor's ``aot_inductor.metadata`` option). :func:`package_metadata` builds that map from an export's metadata,
so every package of ``python -m dacr_learn.export`` and ``python -m dacr_learn.ik.exported`` describes itself: the
binary and its description cannot be separated or mixed up. Keys (all prefixed ``dacr_learn.``; every value a
string, numbers as Python's ``repr`` of a float, lists separated by ``,``):

- ``format`` (:data:`dacr_learn.deploy.export.FORMAT`), ``module`` ("fk", "jacobian", "ik", "refine", …), ``task``
  ("fk", "ik", "ik_refinement", "hardware_fk"), ``dtype`` ("float32" | "float64"), ``robot`` (its name),
  ``torch_version``;
- ``inputs``, ``outputs``: ``name:shape`` per tensor, shapes as ``4x4`` (``""`` for a scalar per row), each with
  a leading batch dim that is not written;
- ``joint_names``, ``joint_units``: the columns of the joint vector q (robot models: ``s<k>.q<j>`` [m] per joint
  length, then ``s<k>.alpha`` [rad] per twisting segment) or of the servo command (hardware models:
  ``servo<id>`` [mm]);
- robot models only: ``feature_names`` (the actuated Clarke features, the columns of ``J_f``), the features'
  limits ``feature_lower`` / ``feature_upper`` (±inf on the ρ columns), ``feature_disks`` (index pairs of the ρ
  columns, ``i j`` per pair) with ``feature_disk_radius`` [m] (‖ρ‖ ≤ d·bend), ``feature_scale`` (a typical range
  per feature), ``robot_length`` [m] (the sum of the nominal segment lengths), and when the Clarke maps are
  affine (no twisting segment) ``decoder_matrix`` (N × D, row major) and ``decoder_offset`` (N): q = A·f + c,
  ``encoder_matrix`` (D × N) and ``encoder_offset`` (D): f = E·q + e;
- ``iterations``, ``position_only`` (IK refinement); ``servo_ids``, ``history`` (hardware models);
- the whole-body control step (task ``whole_body_control``, :mod:`dacr_learn.arm.exported`): ``joint_names`` /
  ``joint_units`` are the arm's joints (URDF names, chain order, rad / m) then the robot's, ``arm_joints`` (their
  count), ``arm_lower``, ``arm_upper`` [rad, m] and ``arm_velocity`` [rad/s, m/s] (URDF), ``mount`` (4 × 4, row
  major) [m], the controller's ``gain``, ``damping``, ``max_step``, ``rotation_length``, ``port_weight``,
  ``rest_gain`` and ``dt`` [s] (absent: no velocity limits), ``port_centre`` [m] and ``port_radius`` [m] (absent:
  no port); the feature entries describe the robot.
"""
from __future__ import annotations

from typing import Any

import torch

from ..clarke_space import ClarkeSpace
from ..folding import affine_probe
from ..models import actuated_columns
from ..robot import RobotSpec

PREFIX = "dacr_learn."


def _numbers(values) -> str:
    return ",".join(repr(float(v)) for v in torch.as_tensor(values, dtype=torch.float64).reshape(-1).tolist())


def _tensors(entries: list) -> str:
    return ",".join(f"{name}:{'x'.join(str(int(d)) for d in shape)}" for name, shape in entries)


def joint_names(spec: RobotSpec) -> tuple[list[str], list[str]]:
    """Names and units of the joint vector's columns: joint lengths [m] per segment, then twists [rad]."""
    names = [f"s{k}.q{j}" for k, seg in enumerate(spec.segments) for j in range(seg.num_joints)]
    twists = [f"s{k}.alpha" for k, seg in enumerate(spec.segments) if seg.twists]
    return names + twists, ["m"] * len(names) + ["rad"] * len(twists)


def robot_entries(spec: RobotSpec) -> dict[str, str]:
    """Joint and feature names, feature limits and (where affine) the Clarke maps of a robot (module docstring)."""
    space = ClarkeSpace(spec)
    limits = space.limits                        # ±inf bounds on the disk coordinates
    names, units = joint_names(spec)
    out = {"joint_names": ",".join(names), "joint_units": ",".join(units),
           "feature_names": ",".join(f"s{k}.{name}" for k, name in actuated_columns(spec)),
           "feature_lower": _numbers(limits.lower), "feature_upper": _numbers(limits.upper),
           "feature_disks": ",".join(f"{i} {j}" for i, j in limits.disks.tolist()),
           "feature_disk_radius": _numbers(limits.radius), "feature_scale": _numbers(limits.scale),
           "robot_length": repr(float(spec.total_length))}
    if space.linear:
        enc_matrix, enc_offset = affine_probe(space.features, spec.num_joints)     # f = q·M + c
        out.update(decoder_matrix=_numbers(space.dec_matrix), decoder_offset=_numbers(space.dec_offset),
                   encoder_matrix=_numbers(enc_matrix.mT), encoder_offset=_numbers(enc_offset))
    return out


def package_metadata(meta: dict[str, Any], name: str) -> dict[str, str]:
    """The flat string map (module docstring) stored in module ``name``'s AOTInductor package, from the export's
    metadata ``meta`` (the dict written to ``metadata.json``; its header, robot and module signatures)."""
    info = meta["modules"][name]
    out = {"format": meta["format"], "module": name, "task": meta["task"], "dtype": meta["dtype"],
           "robot": meta["robot"]["name"], "torch_version": meta["torch_version"],
           "inputs": _tensors(info["inputs"]), "outputs": _tensors(info["outputs"])}
    if meta["task"] == "hardware_fk":
        out.update(joint_names=",".join(f"servo{i}" for i in meta["servo_ids"]),
                   joint_units=",".join("mm" for _ in meta["servo_ids"]),
                   servo_ids=",".join(str(i) for i in meta["servo_ids"]), history=str(bool(meta["history"])).lower())
    else:
        out.update(robot_entries(RobotSpec.from_dict(meta["robot"])))
    if meta["task"] == "whole_body_control":
        arm, names, units = meta["arm"], *joint_names(RobotSpec.from_dict(meta["robot"]))
        arm_units = ["m" if t == "prismatic" else "rad" for t in arm["joint_types"]]
        out.update(joint_names=",".join([*arm["joint_names"], *names]), joint_units=",".join([*arm_units, *units]),
                   arm_joints=str(len(arm["joint_names"])), arm_lower=_numbers(arm["lower"]),
                   arm_upper=_numbers(arm["upper"]), arm_velocity=_numbers(arm["velocity"]),
                   mount=_numbers(arm["mount"]),
                   **{k: repr(float(v)) for k, v in meta["control"].items() if v is not None})
        if meta["port"] is not None:
            out.update(port_centre=_numbers(meta["port"]["centre"]), port_radius=repr(float(meta["port"]["radius"])))
    if meta["task"] == "ik_refinement":
        out.update(iterations=str(meta["iterations"]), position_only=str(bool(meta["position_only"])).lower())
    return {PREFIX + k: v for k, v in out.items()}
