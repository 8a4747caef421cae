"""Calibrated CC model: the tracked marker in the tip frame, on the axis or off it (``lateral_marker``).

References: the marker as the tip pose applied to a homogeneous point (another code path than
``marker_point``), the previous model's formula p + t·z_tip, and the CC model's symmetry under a
common rotation of the joint angles (which is why the lateral offset is not traded against it).
"""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from conftest import roundoff_tol

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

ROBOT = Path(__file__).resolve().parents[1] / "configs" / "robots" / "ftdcr_v4.yaml"
TIP_SCALE = 0.2                                   # [m] magnitude of the tip coordinates
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def spec() -> RobotSpec:
    return RobotSpec.from_yaml(ROBOT)


def _displacements(spec: RobotSpec, n: int, seed: int) -> torch.Tensor:
    """Joint displacements (n, N) [m] of random bends (Clarke coordinates up to ±3 mm per segment)."""
    g = torch.Generator().manual_seed(seed)
    m = spec.num_segments
    feat = torch.zeros(n, m, 4, dtype=torch.float64)
    feat[..., :2] = (torch.rand(n, m, 2, generator=g, dtype=torch.float64) - 0.5) * 0.006
    feat[..., 2] = torch.tensor([s.length for s in spec.segments], dtype=torch.float64)
    dec = ClarkeDecoder(spec)
    return dec(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - dec(feat)


def _cc_model(spec: RobotSpec, lateral: bool, marker_mm=(3.0, -2.0, 8.0)) -> CalibratedCC:
    """A CalibratedCC with non-trivial physical parameters (float64)."""
    cc = CalibratedCC(spec, compliance=1e-7, lateral_marker=lateral)
    f64 = dict(dtype=torch.float64)
    with torch.no_grad():
        cc.encoder.log_radius_scale.copy_(torch.tensor([0.05, -0.03, 0.02], **f64))
        cc.encoder.rotation.copy_(torch.tensor([0.02, -0.04, 0.03], **f64))
        cc.base_tilt.copy_(torch.tensor([0.03, -0.02], **f64))
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005], **f64))
        cc.tip_offset.fill_(marker_mm[2] * 1e-3)
        if lateral:
            cc.marker_lateral.copy_(torch.tensor(marker_mm[:2], **f64) * 1e-3)
    return cc


def test_axial_marker_is_the_previous_model(spec):
    cc = _cc_model(spec, lateral=False)
    assert "marker_lateral" not in cc.state_dict() and "marker_lateral_xy_mm" not in cc.report()
    assert torch.equal(cc.marker_offset(), torch.tensor([0.0, 0.0, 8e-3], dtype=torch.float64))
    x = _displacements(spec, 20, 0)
    with torch.no_grad():
        pose = forward_kinematics(spec, cc.encoder(x))
        ref = cc.to_world(pose[..., :3, 3] + pose[..., :3, 2] * cc.tip_offset)   # the formula before
        assert (cc(x) - ref).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)


def test_lateral_marker_is_the_tip_pose_applied_to_the_marker(spec):
    cc = _cc_model(spec, lateral=True)
    assert cc.report()["marker_lateral_xy_mm"] == [3.0, -2.0]
    x = _displacements(spec, 20, 1)
    with torch.no_grad():
        pose = forward_kinematics(spec, cc.encoder(x))
        point = torch.tensor([3e-3, -2e-3, 8e-3, 1.0], dtype=torch.float64)
        ref = cc.to_world((pose @ point)[..., :3])
        got = cc(x)
        assert (got - ref).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)
        axial = _cc_model(spec, lateral=False)(x)
        assert (got - axial).norm(dim=-1).max() > 1e-3, "the lateral offset moves bent tips"


@pytest.mark.parametrize("lateral", [False, True])
def test_state_dict_round_trip_keeps_the_marker_model(spec, lateral):
    cc = _cc_model(spec, lateral)
    loaded = CalibratedCC.from_state_dict(spec, cc.state_dict())
    assert loaded.lateral_marker == lateral
    x = _displacements(spec, 10, 2)
    with torch.no_grad():
        assert (loaded(x) - cc(x)).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)
    with pytest.raises(RuntimeError, match="marker_lateral"):
        CalibratedCC(spec, lateral_marker=not lateral).load_state_dict(cc.state_dict())


def test_common_joint_rotation_turns_the_whole_tip_and_the_lateral_marker(spec):
    """Rotating every segment's joint angles by φ maps the tips to Rz(φ)·(p + R·Rz(−φ)·d): the
    lateral offset turns by −φ relative to the tip cloud, so it is not degenerate with the joint
    rotations (the model has no separate base yaw that could undo the turn of the cloud)."""
    phi = 0.4
    turned, ref = _cc_model(spec, True), _cc_model(spec, True)
    rz = torch.tensor([[math.cos(phi), -math.sin(phi), 0.0], [math.sin(phi), math.cos(phi), 0.0], [0.0, 0.0, 1.0]],
                      dtype=torch.float64)
    with torch.no_grad():
        for cc in (turned, ref):
            cc.base_tilt.zero_()
            cc.base_translation.zero_()
        turned.encoder.rotation.add_(phi)
        ref.marker_lateral.copy_(rz[:2, :2].T @ turned.marker_lateral)
        x = _displacements(spec, 20, 3)
        assert (turned(x) - ref(x) @ rz.T).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE, ulps=256)
        assert (turned(x) - ref(x)).abs().max() > 1e-2       # and the turn is visible


def test_gradcheck_in_the_marker_parameters(spec):
    cc = _cc_model(spec, lateral=True)
    x = _displacements(spec, 4, 4)

    def tips(lateral, axial):
        return torch.func.functional_call(cc, {"marker_lateral": lateral, "tip_offset": axial}, (x,))

    args = (cc.marker_lateral.detach().clone().requires_grad_(), cc.tip_offset.detach().clone().requires_grad_())
    assert torch.autograd.gradcheck(tips, args)


def test_fit_recovers_a_lateral_marker(spec):
    """Tips of a model with the marker 3.6 mm off the axis (+0.05 mm noise): fitted together with the joint
    rotations, base tilt and translation (the parameters it could trade against), the lateral model
    recovers the offset; the axial model cannot represent it. (The radii, compliance and pretension are
    held at the truth to keep the test short.)"""
    truth = _cc_model(spec, lateral=True)
    x = _displacements(spec, 40, 5)
    with torch.no_grad():
        tip = truth(x) + 5e-5 * torch.randn(len(x), 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    frozen = ("encoder.log_radius_scale", "encoder.log_compliance", "encoder.pretension")
    rms = {}
    for lateral in (True, False):
        cc = CalibratedCC.from_state_dict(spec, truth.state_dict()) if lateral else _cc_model(spec, False)
        with torch.no_grad():
            for p in (cc.encoder.rotation, cc.base_tilt, cc.base_translation, cc.tip_offset):
                p.zero_()
            if lateral:
                cc.marker_lateral.zero_()
        rms[lateral] = fit_cc(cc, x, tip, max_iter=60, frozen=frozen)["rms_m"]
        if lateral:
            assert (cc.marker_offset() - truth.marker_offset()).abs().max() < 1e-4
            assert (cc.encoder.rotation - truth.encoder.rotation).abs().max() < 1e-3
    noise = 5e-5 * math.sqrt(3)                  # RMS norm of the noise [m]
    assert rms[True] < 1.1 * noise and rms[False] > 5 * noise


def test_inference_module_includes_the_lateral_marker():
    """The deployed FK (hardware.deploy.inference) computes the library model's tips with a lateral marker."""
    from hardware_testkit import TIP_SCALE as DEPLOY_SCALE
    from hardware_testkit import batch_prediction, command_recording, synthetic_model

    from dacr_learn.hardware.deploy.inference import HardwareFK

    model = synthetic_model(history=False)
    assert model.cc.lateral_marker
    with torch.no_grad():
        model.cc.marker_lateral.copy_(torch.tensor([4e-3, -3e-3], dtype=torch.float64))
    rec = command_recording(60, 5)
    got = HardwareFK(model, torch.float64)(1e3 * rec.servo)[0]
    assert (got - batch_prediction(model, rec)).abs().max() <= roundoff_tol(torch.float32, DEPLOY_SCALE)
