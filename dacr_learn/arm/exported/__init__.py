"""The whole-body control step of an arm carrying a continuum robot as an exported module, for a controller without
Python (cpp/: ``dacr::WholeBodyStep``, docs/cpp.md), written and verified like every other export
(:func:`dacr_learn.deploy.export.write_export`: ``step.pt2`` [and ``step.aoti.pt2``], ``metadata.json``, the
package's own metadata map).

:class:`WholeBodyStep`: one step of :class:`~dacr_learn.arm.control.WholeBodyController` in joints, float64:
(q (B, n + N) [the arm's joints in chain order, rad / m, then the robot's joint vector, m / rad],
target (B, 4, 4) [m, arm base frame], feedforward (B, 6) (Δp [m], Δφ [rad] of the target over the step)) →
q' (B, n + N). The gains, the port and the control period are fixed at export (metadata ``gain``, ``damping``,
``max_step``, ``rotation_length``, ``port_weight``, ``rest_gain``, ``dt``, ``port_centre``, ``port_radius``).

    python -m dacr_learn.arm.exported --arm configs/arms/panda.urdf --arm-tip panda_link8 \\
        --mount configs/arms/panda_mount.npy --robot configs/robots/tdcr_3seg_coupled.yaml --out exports/arm_step
    step = dacr_learn.load_exported("exports/arm_step", "step")
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ...checks import F64
from ...deploy.export import FORMAT, MAX_BATCH, file_sha256, output_folder, write_export
from ..composite import Composite
from ..control import Port, WholeBodyConfig, WholeBodyController

TASK = "whole_body_control"


class WholeBodyStep(nn.Module):
    """One whole-body control step in joints (module docstring): ``controller.step`` as a module."""

    def __init__(self, controller: WholeBodyController):
        super().__init__()
        self.controller = controller

    def forward(self, q: Tensor, target: Tensor, feedforward: Tensor) -> Tensor:
        return self.controller.step(q, target, feedforward)


def examples(model: Composite, n: int = 64, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Inputs the export is verified on: admissible joints q (n, n_arm + N), pose targets near them (n, 4, 4) [m]
    and small feedforwards (n, 6)."""
    g = torch.Generator().manual_seed(seed)
    lim = model.limits
    x = lim.sample(n, g)
    near = lim.project(x + 0.05 * lim.scale * torch.randn(x.shape, generator=g, dtype=F64))
    return model.joints(x), model.pose_of_variables(near), 1e-4 * torch.randn(n, 6, generator=g, dtype=F64)


def export_control_step(model: Composite, out: str | Path, *, config: WholeBodyConfig | None = None,
                        port: Port | None = None, aoti: bool = True,
                        sources: dict[str, str | Path] | None = None) -> dict[str, Any]:
    """Export the whole-body step of ``model`` with ``config`` and ``port`` as the module ``step`` into ``out``,
    verified against the eager controller on :func:`examples`; returns the metadata (:func:`step_metadata`, completed
    by :func:`~dacr_learn.deploy.export.write_export`). ``config``: default :class:`~dacr_learn.arm.control.
    WholeBodyConfig` (). ``sources``: the files the model was built from (name → path), recorded with their sha256.
    ValueError for a robot without a pose (the step's target is a pose)."""
    if not model.has_rotation:
        raise ValueError("robot: the exported whole-body step needs a robot with a tip pose (its target is a pose)")
    config = WholeBodyConfig() if config is None else config
    controller = WholeBodyController(model, config, port)
    module = WholeBodyStep(controller).eval()
    out = output_folder(out)
    meta = step_metadata(controller, sources)
    return write_export(out, meta, {"step": module}, {"step": examples(model)}, {"step": module}, aoti=aoti,
                        autotune=False, against="the eager whole-body controller")


def step_metadata(controller: WholeBodyController, sources: dict[str, str | Path] | None = None) -> dict[str, Any]:
    """The export's metadata (``metadata.json`` before the files are added) of ``controller``'s step: the arm (joint
    names, types, URDF limits, mount), the port, the gains and the module's signature."""
    model, config, port = controller.model, controller.config, controller.port
    arm, n = model.arm, model.num_joints
    velocity = arm.chain.get_joint_velocity_limits()[1]
    return {"format": FORMAT, "task": TASK, "dtype": "float64", "torch_version": torch.__version__,
            "max_batch": MAX_BATCH, "aoti_autotune": False, "robot": model.robot.spec.to_dict(), "features": "clarke",
            "sources": {k: {"path": str(p), "sha256": file_sha256(p)} for k, p in (sources or {}).items()},
            "arm": {"tip": arm.tip, "joint_names": list(arm.joint_names), "joint_types": list(arm.joint_types),
                    "lower": arm.limits.lower.tolist(), "upper": arm.limits.upper.tolist(),
                    "velocity": [float(v) for v in velocity], "mount": model.mount.tolist()},
            "port": None if port is None else {"centre": list(port.centre), "radius": port.radius},
            "control": {"gain": config.gain, "damping": config.damping, "max_step": config.max_step,
                        "rotation_length": controller.weight, "port_weight": config.port_weight,
                        "rest_gain": config.rest_gain, "dt": config.dt},
            "modules": {"step": {"inputs": [["q", [n]], ["target", [4, 4]], ["feedforward", [6]]],
                                 "outputs": [["q", [n]]]}}}
