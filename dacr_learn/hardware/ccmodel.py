"""Calibrated constant-curvature model of a tendon robot: joint displacements → tip position.

    x (..., N) [m] ──SlackAwareEncoder──▶ features (..., m, 4) ──forward_kinematics──▶ T_tip = (R_tip, p_tip)
    tip = R_base · (p_tip + R_tip · d_marker) + t_base   (motion-capture frame, metres)

The fitted physical parameters, the ``strain`` variant (``pretension_strain=True``) and their scores: docs/hardware.md,
"The calibrated CC model"; the marker offset d_marker is (x, y, t) in the tip frame (``lateral_marker=True``, the
default) or (0, 0, t). Segment lengths stay nominal (they trade off against the radii and made the fit degenerate).

The lateral offset is identifiable: the CC tip frame has no twist, so (x, y) acts like a base translation
on a straight robot and is separated from it by the bends; a common rotation of the joint angles turns
the offset with the whole tip cloud, so the two are not traded against each other.
"""
from __future__ import annotations

import time
from collections.abc import Mapping

import torch
from pytorch_kinematics.transforms import euler_angles_to_matrix
from torch import Tensor, nn

from ..body import BodyPoints, body_of_points, check_points_per_segment
from ..kinematics import backbone_points, forward_kinematics
from ..robot import RobotSpec
from .slack import SlackAwareEncoder


class CalibratedCC(nn.Module):
    """Joint displacements (..., N) [m] → tip position (..., 3) [m] in the motion-capture frame."""

    def __init__(self, spec: RobotSpec, compliance: float = 1e-6, lateral_marker: bool = True,
                 pretension_strain: bool = False):
        super().__init__()
        self.spec = spec
        self.encoder = SlackAwareEncoder(spec, compliance=compliance, strain=pretension_strain)
        f64 = dict(dtype=torch.float64)
        self.base_tilt = nn.Parameter(torch.zeros(2, **f64))   # about x, then y; yaw = joint rotations
        self.base_translation = nn.Parameter(torch.zeros(3, **f64))
        self.tip_offset = nn.Parameter(torch.zeros((), **f64))                # along the tip axis z_tip
        self.lateral_marker = bool(lateral_marker)
        if self.lateral_marker:
            self.marker_lateral = nn.Parameter(torch.zeros(2, **f64))      # (x, y) in the tip frame

    @classmethod
    def from_state_dict(cls, spec: RobotSpec, state: Mapping[str, Tensor]) -> CalibratedCC:
        """The model of a saved ``state_dict()`` (with or without the lateral marker offset and the
        pretension strain)."""
        model = cls(spec, lateral_marker="marker_lateral" in state,
                    pretension_strain="encoder.pretension_strain" in state)
        model.load_state_dict(state)
        return model

    def marker_offset(self) -> Tensor:
        """Marker position d (3,) [m] in the tip frame: (x, y, t); x = y = 0 without ``lateral_marker``."""
        lateral = self.marker_lateral if self.lateral_marker else self.tip_offset.new_zeros(2)
        return torch.cat([lateral, self.tip_offset.reshape(1)])

    def marker_point(self, pose: Tensor) -> Tensor:
        """Tip poses (..., 4, 4) [m] in the robot base frame → marker points p + R·d (..., 3) [m], same frame."""
        return pose[..., :3, 3] + pose[..., :3, :3] @ self.marker_offset().to(pose.dtype)

    def base_rotation(self) -> Tensor:
        """Base tilt R = Rx·Ry (yaw is not separate: it equals a common rotation of the joints)."""
        return euler_angles_to_matrix(torch.cat([self.base_tilt, self.base_tilt.new_zeros(1)]), "XYZ")

    def to_world(self, p: Tensor) -> Tensor:
        """Points (..., 3) in the robot base frame → motion-capture frame."""
        r, t = self.base_rotation().to(p.dtype), self.base_translation.to(p.dtype)
        return p @ r.mT + t

    def tip_from_features(self, features: Tensor) -> Tensor:
        """Features (..., m, 4) (nominal-spec convention) → tip marker position (..., 3) [m]."""
        return self.to_world(self.marker_point(forward_kinematics(self.spec, features)))

    def forward(self, x: Tensor) -> Tensor:
        return self.tip_from_features(self.encoder(x))

    def backbone(self, x: Tensor, points_per_segment: int = 12) -> Tensor:
        """Backbone points (..., 1 + m·K, 3) [m] in the motion-capture frame, for drawing."""
        return self.to_world(backbone_points(self.spec, self.encoder(x), points_per_segment))

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The calibrated model's body of displacements x (..., N) [m]: the CC arcs of the fitted encoder's
        features, in the motion-capture frame (:mod:`dacr_learn.body` layout; radii of the nominal robot file)."""
        return body_of_points(self.spec, self.backbone(x, check_points_per_segment(points_per_segment)),
                              points_per_segment)

    def report(self) -> dict:
        """Fitted physical parameters in readable units (mm, deg)."""
        enc = self.encoder
        with torch.no_grad():
            out = {
                "effective_radius_mm": [round(v * 1e3, 3) for v in enc.effective_radius().tolist()],
                "joint_rotation_deg": [round(v, 2) for v in torch.rad2deg(enc.rotation).tolist()],
                "compliance_EI_over_EA_mm2": round(enc.log_compliance.exp().item() * 1e6, 4),
                "pretension_mm": round(enc.pretension.item() * 1e3, 3),
                "base_tilt_xy_deg": [round(v, 2) for v in torch.rad2deg(self.base_tilt).tolist()],
                "base_translation_mm": [round(v * 1e3, 2) for v in self.base_translation.tolist()],
                "tip_marker_offset_mm": round(self.tip_offset.item() * 1e3, 2),
            }
            if enc.strain:
                member = nn.functional.one_hot(enc.segment_of_joint, self.spec.num_segments).to(enc.lengths.dtype)
                per_segment = member.T @ enc.tendon_pretension() / member.sum(0)       # mean per segment
                out["pretension_per_segment_mm"] = [round(v * 1e3, 3) for v in per_segment.tolist()]
            if self.lateral_marker:
                out["marker_lateral_xy_mm"] = [round(v * 1e3, 2) for v in self.marker_lateral.tolist()]
            return out


# Typical magnitude of each parameter: the fit works on parameter / scale, so that the
# L-BFGS steps are well conditioned across metres, millimetre pretensions and log-radii.
FIT_SCALES = {"encoder.log_radius_scale": 0.1, "encoder.rotation": 0.05, "encoder.log_compliance": 1.0,
               "encoder.pretension": 1e-4, "base_tilt": 0.02, "base_translation": 1e-3, "tip_offset": 1e-3,
               "marker_lateral": 1e-3, "encoder.pretension_strain": 1e-4}


def fit_cc(model: CalibratedCC, x: Tensor, tip: Tensor, max_iter: int = 200, frozen: tuple[str, ...] = (),
           scales: Mapping[str, float] | None = None) -> dict:
    """Least-squares fit of the physical parameters to (x (n, N), tip (n, 3)) [m] with L-BFGS, on parameter / scale
    (:data:`FIT_SCALES`, added to or overridden by ``scales``); ``frozen`` parameters keep their values; the base
    translation starts at the mean residual. Returns {"seconds", "rms_m"}.
    """
    start = time.perf_counter()
    scale = {**FIT_SCALES, **(scales or {})}
    unscaled = [n for n, _ in model.named_parameters() if n not in scale and n not in frozen]
    if unscaled:
        raise ValueError(f"fit_cc: parameters {unscaled} have no fit scale; expected them in scales= "
                         f"(known: {sorted(scale)})")
    with torch.no_grad():
        model.base_translation += (tip - model(x)).mean(0)
    base = {n: p.detach().clone() for n, p in model.named_parameters()}
    free = [n for n in base if n not in frozen]
    z = {n: torch.zeros_like(base[n], requires_grad=True) for n in free}
    opt = torch.optim.LBFGS(list(z.values()), max_iter=max_iter, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-10, tolerance_change=1e-14)

    def params() -> dict:
        return {n: base[n] + scale[n] * z[n] if n in z else base[n] for n in base}

    def closure():
        opt.zero_grad()
        pred = torch.func.functional_call(model, params(), (x,))
        loss = ((pred - tip) ** 2).sum(-1).mean() * 1e6
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        for n, value in params().items():
            model.get_parameter(n).copy_(value)
        rms = ((model(x) - tip) ** 2).sum(-1).mean().sqrt().item()
    return {"seconds": time.perf_counter() - start, "rms_m": rms}
