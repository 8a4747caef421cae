"""The calibrated CC model (dacr_learn.hardware.ccmodel).

The tracked marker in the tip frame, on the axis or off it (``lateral_marker``). References: the marker as the tip
pose applied to a homogeneous point (another code path than ``marker_point``), the previous model's formula
p + t·z_tip, and the CC model's symmetry under a common rotation of the joint angles (which is why the lateral
offset is not traded against it).

A pretension that grows with the tendon path length (``pretension_strain``): tendon i's pretension stretch is
p_i = p + s·(L_i/L̄ − 1). References: the model without the option fed with commands shifted by s·(L_i/L̄ − 1)
(another code path), the option off / s = 0 being the model before, a state-dict round trip, gradcheck in s.
"""
from __future__ import annotations

import math

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import V4_TIP_SCALE, strained_cc

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


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


def test_axial_marker_is_the_previous_model(v4_spec):
    cc = _cc_model(v4_spec, lateral=False)
    assert "marker_lateral" not in cc.state_dict() and "marker_lateral_xy_mm" not in cc.report()
    assert torch.equal(cc.marker_offset(), torch.tensor([0.0, 0.0, 8e-3], dtype=torch.float64))
    x = _displacements(v4_spec, 20, 0)
    with torch.no_grad():
        pose = forward_kinematics(v4_spec, cc.encoder(x))
        ref = cc.to_world(pose[..., :3, 3] + pose[..., :3, 2] * cc.tip_offset)   # the formula before
        assert (cc(x) - ref).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)


def test_lateral_marker_is_the_tip_pose_applied_to_the_marker(v4_spec):
    cc = _cc_model(v4_spec, lateral=True)
    assert cc.report()["marker_lateral_xy_mm"] == [3.0, -2.0]
    x = _displacements(v4_spec, 20, 1)
    with torch.no_grad():
        pose = forward_kinematics(v4_spec, cc.encoder(x))
        point = torch.tensor([3e-3, -2e-3, 8e-3, 1.0], dtype=torch.float64)
        ref = cc.to_world((pose @ point)[..., :3])
        got = cc(x)
        assert (got - ref).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)
        axial = _cc_model(v4_spec, lateral=False)(x)
        assert (got - axial).norm(dim=-1).max() > 1e-3, "the lateral offset moves bent tips"


@pytest.mark.parametrize("lateral", [False, True])
def test_state_dict_round_trip_keeps_the_marker_model(v4_spec, lateral):
    cc = _cc_model(v4_spec, lateral)
    loaded = CalibratedCC.from_state_dict(v4_spec, cc.state_dict())
    assert loaded.lateral_marker == lateral
    x = _displacements(v4_spec, 10, 2)
    with torch.no_grad():
        assert (loaded(x) - cc(x)).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)
    with pytest.raises(RuntimeError, match="marker_lateral"):
        CalibratedCC(v4_spec, lateral_marker=not lateral).load_state_dict(cc.state_dict())


def test_common_joint_rotation_turns_the_whole_tip_and_the_lateral_marker(v4_spec):
    """Rotating every segment's joint angles by φ maps the tips to Rz(φ)·(p + R·Rz(−φ)·d): the
    lateral offset turns by −φ relative to the tip cloud, so it is not degenerate with the joint
    rotations (the model has no separate base yaw that could undo the turn of the cloud)."""
    phi = 0.4
    turned, ref = _cc_model(v4_spec, True), _cc_model(v4_spec, True)
    rz = torch.tensor([[math.cos(phi), -math.sin(phi), 0.0], [math.sin(phi), math.cos(phi), 0.0], [0.0, 0.0, 1.0]],
                      dtype=torch.float64)
    with torch.no_grad():
        for cc in (turned, ref):
            cc.base_tilt.zero_()
            cc.base_translation.zero_()
        turned.encoder.rotation.add_(phi)
        ref.marker_lateral.copy_(rz[:2, :2].T @ turned.marker_lateral)
        x = _displacements(v4_spec, 20, 3)
        assert (turned(x) - ref(x) @ rz.T).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE, ulps=256)
        assert (turned(x) - ref(x)).abs().max() > 1e-2       # and the turn is visible


def test_gradcheck_in_the_marker_parameters(v4_spec):
    cc = _cc_model(v4_spec, lateral=True)
    x = _displacements(v4_spec, 4, 4)

    def tips(lateral, axial):
        return torch.func.functional_call(cc, {"marker_lateral": lateral, "tip_offset": axial}, (x,))

    args = (cc.marker_lateral.detach().clone().requires_grad_(), cc.tip_offset.detach().clone().requires_grad_())
    assert torch.autograd.gradcheck(tips, args)


def test_fit_recovers_a_lateral_marker(v4_spec):
    """Tips of a model with the marker 3.6 mm off the axis (+0.05 mm noise): fitted together with the joint
    rotations, base tilt and translation (the parameters it could trade against), the lateral model
    recovers the offset; the axial model cannot represent it. (The radii, compliance and pretension are
    held at the truth to keep the test short.)"""
    truth = _cc_model(v4_spec, lateral=True)
    x = _displacements(v4_spec, 40, 5)
    with torch.no_grad():
        tip = truth(x) + 5e-5 * torch.randn(len(x), 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    frozen = ("encoder.log_radius_scale", "encoder.log_compliance", "encoder.pretension")
    rms = {}
    for lateral in (True, False):
        cc = CalibratedCC.from_state_dict(v4_spec, truth.state_dict()) if lateral else _cc_model(v4_spec, False)
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


# --------------------------------------------------------------------------------------------------
# Pretension strain
# --------------------------------------------------------------------------------------------------


def _x(v4_train_head):
    spec, smap, rec = v4_train_head
    return smap.displacements(spec, rec)


def test_without_strain_every_tendon_has_the_common_pretension(v4_train_head):
    cc = strained_cc(v4_train_head[0], strain=False)
    assert "encoder.pretension_strain" not in cc.state_dict() and "pretension_per_segment_mm" not in cc.report()
    assert torch.equal(cc.encoder.tendon_pretension(), torch.full((9,), 3e-4, dtype=torch.float64))


def test_strain_is_a_path_length_proportional_shift_of_the_commands(v4_train_head):
    spec, x = v4_train_head[0], _x(v4_train_head)
    strained, plain = strained_cc(spec, strain=True), strained_cc(spec, strain=False)
    path = plain.encoder.path_length
    shift = 5e-4 * (path / path.mean() - 1)
    with torch.no_grad():
        got, ref = strained(x), plain(x + shift)
    assert (got - ref).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)
    assert (got - plain(x)).abs().max() > 1e-4          # the option changes the model (0.1 mm)


def test_zero_strain_is_the_model_without_it(v4_train_head):
    spec, x = v4_train_head[0], _x(v4_train_head)
    with torch.no_grad():
        diff = (strained_cc(spec, strain=True, s=0.0)(x) - strained_cc(spec, strain=False)(x)).abs().max()
    assert diff <= roundoff_tol(torch.float64, V4_TIP_SCALE)


def test_pure_strain_stretches_each_tendon_in_proportion_to_its_length(v4_train_head):
    enc = strained_cc(v4_train_head[0], strain=True, p=4e-4, s=4e-4).encoder
    ratio = enc.tendon_pretension() / enc.path_length
    assert (ratio - ratio.mean()).abs().max() <= roundoff_tol(torch.float64, ratio.abs().max().item())
    assert len(set(enc.path_length.tolist())) == 3      # three path lengths on a 3-segment robot: a real test


def test_state_dict_round_trip_keeps_the_strain(v4_train_head):
    spec, x = v4_train_head[0], _x(v4_train_head)
    cc = strained_cc(spec, strain=True)
    again = CalibratedCC.from_state_dict(spec, cc.state_dict())
    assert again.encoder.strain and "pretension_per_segment_mm" in again.report()
    with torch.no_grad():
        assert (again(x) - cc(x)).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)


def test_gradcheck_in_the_strain(v4_train_head):
    spec, x = v4_train_head[0], _x(v4_train_head)[:20]
    cc = strained_cc(spec, strain=True)
    names = ["encoder.pretension_strain"]
    params = {n: p.detach().clone() for n, p in cc.named_parameters()}

    def tip(s):
        return torch.func.functional_call(cc, {**params, names[0]: s}, (x,))

    assert torch.autograd.gradcheck(tip, (params[names[0]].clone().requires_grad_(True),), eps=1e-7, atol=1e-6)


def test_fit_recovers_the_strain(v4_train_head):
    spec, x = v4_train_head[0], _x(v4_train_head)
    truth = strained_cc(spec, strain=True, s=6e-4)
    with torch.no_grad():
        tip = truth(x)
    cc = CalibratedCC(spec, pretension_strain=True)
    fit = fit_cc(cc, x, tip)
    assert fit["rms_m"] < 1e-4                           # 0.1 mm on a 0.2 m robot
    assert abs(cc.encoder.pretension_strain.item() - 6e-4) < 1e-4
