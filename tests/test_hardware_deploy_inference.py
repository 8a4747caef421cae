"""The deployed FK and Jacobian modules (dacr_learn.hardware.deploy.inference) against the library model.

- The CC segment pose (:func:`~dacr_learn.hardware.deploy.inference.cc_segment_poses`)
  against :func:`~dacr_learn.kinematics.cc_transform`, with finite gradients at zero bending.
- The chained tip and its closed-form ∂tip/∂ρ (:func:`~dacr_learn.hardware.deploy.inference.cc_tip_and_jacobian`)
  against the tip of cc_transform products and autograd's Jacobian of it, straight segments included.
- HardwareFK / HardwareJacobian of a small synthetic model (tests/hardware_testkit.py) equal the library model run
  causally (play state passed on) and autograd in float64; HardwareFK computes the library model's tips with a
  lateral marker, a pretension strain, and the stored σ model.
"""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import (
    TIP_SCALE,
    V4_TIP_SCALE,
    batch_prediction,
    command_recording,
    sigma_roundoff_tol,
    strained_cc,
    synthetic_model,
)

from dacr_learn.hardware.deploy.checkpoint import HardwareModel
from dacr_learn.hardware.deploy.inference import (
    HardwareFK,
    HardwareJacobian,
    cc_segment_poses,
    cc_tip_and_jacobian,
    cc_twist_directions,
)
from dacr_learn.hardware.deploy.uncertainty import SigmaModel
from dacr_learn.hardware.learned import cc_as_residual, make_split
from dacr_learn.kinematics import cc_transform

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_segment_pose_from_twist_is_cc_transform(dtype):
    g = torch.Generator().manual_seed(0)
    radius, length = torch.tensor([0.005, 0.004, 0.0045], dtype=F64), torch.tensor([0.08, 0.07, 0.06], dtype=F64)
    rho = 0.004 * (2 * torch.rand(400, 3, 2, generator=g, dtype=F64) - 1)
    rho[:50] *= 1e-6                                           # nearly straight
    rho[50:60] = 0.0                                           # straight
    got = cc_segment_poses(rho.to(dtype), radius.to(dtype), length.to(dtype))
    ref = cc_transform(rho / radius.unsqueeze(-1), length.expand(400, 3))
    assert (got.double() - ref).abs().max() <= roundoff_tol(dtype, 1.0, ulps=16)


def test_segment_pose_gradient_is_finite_and_right_at_zero_bending():
    radius, length = torch.tensor([0.005], dtype=F64), torch.tensor([0.08], dtype=F64)
    def pose(rho):
        return cc_segment_poses(rho, radius, length)

    def reference(rho):
        return cc_transform(rho / radius.unsqueeze(-1), length)

    for rho in (torch.zeros(1, 2, dtype=F64), torch.tensor([[1e-3, -2e-3]], dtype=F64)):
        got = torch.autograd.functional.jacobian(pose, rho)
        ref = torch.autograd.functional.jacobian(reference, rho)
        assert bool(torch.isfinite(got).all())
        assert (got - ref).abs().max() <= roundoff_tol(F64, float(ref.abs().max()), ulps=1024)


def test_tip_jacobian_in_closed_form_is_autograds_of_the_cc_chain():
    """Three segments, a base pose and a marker offset; ρ with straight (0) and nearly straight (1e-9 m)
    segments, where s, f and their derivatives take the Taylor branch."""
    g = torch.Generator().manual_seed(1)
    radius, length = torch.tensor([0.005, 0.004, 0.0045], dtype=F64), torch.tensor([0.08, 0.07, 0.06], dtype=F64)
    angle = torch.tensor(0.3, dtype=F64)
    base = torch.eye(4, dtype=F64)
    base[:2, :2] = torch.tensor([[angle.cos(), -angle.sin()], [angle.sin(), angle.cos()]])
    base[:3, 3] = torch.tensor([0.01, -0.02, 0.3], dtype=F64)
    marker = torch.tensor([0.004, -0.002, 0.01, 1.0], dtype=F64)
    rho = 0.004 * (2 * torch.rand(6, 3, 2, generator=g, dtype=F64) - 1)
    rho[0, 1] = 0.0
    rho[1, 0] = 1e-9
    rho[2] = 0.0

    def reference_tip(r):                                      # base · T₁ T₂ T₃ · marker with cc_transform
        chain = base
        for k in range(3):
            chain = chain @ cc_transform(r[k] / radius[k], length[k])
        return (chain @ marker)[:3]

    tip, jac = cc_tip_and_jacobian(rho, radius, length, cc_twist_directions(radius), base, marker)
    for b in range(rho.shape[0]):
        ref_tip = reference_tip(rho[b])
        ref_jac = torch.autograd.functional.jacobian(reference_tip, rho[b])             # (3, m, 2)
        assert (tip[b] - ref_tip).abs().max() <= roundoff_tol(F64, 1.0, ulps=64)
        assert bool(torch.isfinite(jac[b]).all())
        tol = roundoff_tol(F64, float(ref_jac.abs().max()), ulps=1024)
        assert (jac[b].permute(2, 0, 1) - ref_jac).abs().max() <= tol


# --------------------------------------------------------------------------------------------------
# HardwareFK and HardwareJacobian against the library model
# --------------------------------------------------------------------------------------------------


def _causal(fk, servo_mm: torch.Tensor, history: bool) -> torch.Tensor:
    """Run an FK module command by command, passing the play state on."""
    if not history:
        return fk(servo_mm)[0]
    state, tips = fk.initial_state(servo_mm[:1]) if hasattr(fk, "initial_state") else None, []
    for t in range(servo_mm.shape[0]):
        tip, _, state = fk(servo_mm[t:t + 1], state)
        tips.append(tip)
    return torch.cat(tips)


@pytest.mark.parametrize("history", [False, True])
def test_inference_module_equals_the_library_model_run_causally(history):
    model = synthetic_model(history)
    rec = command_recording(120, 5, amplitude=4e-3)          # partly outside the training commands
    fk = HardwareFK(model, torch.float64)
    got = _causal(fk, 1e3 * rec.servo, history)
    # The library model runs its kinematics in float32: agreement to float32 rounding at tip scale.
    assert (got - batch_prediction(model, rec)).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)


@pytest.mark.parametrize("history", [False, True])
def test_jacobian_matches_autograd_in_float64(history):
    model = synthetic_model(history)
    with torch.no_grad():                                # a marker off the tip axis (CalibratedCC's default kind)
        model.cc.marker_lateral.copy_(torch.tensor([4e-3, -3e-3], dtype=torch.float64))
    fk, jac = HardwareFK(model, torch.float64), HardwareJacobian(model, torch.float64)
    servo = 1e3 * command_recording(40, 7, amplitude=5e-3).servo[::8]
    state = fk.initial_state(servo) + 3e-5 * torch.randn(servo.shape[0], 2, 2, dtype=torch.float64,
                                                         generator=torch.Generator().manual_seed(0))
    args = (state,) if history else ()
    tip, j = jac(servo, *args)[:2]
    assert (tip - fk(servo, *args)[0]).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE, ulps=1024)
    for b in range(servo.shape[0]):
        ref = torch.func.jacrev(lambda s, b=b: fk(s.unsqueeze(0), *(a[b:b + 1] for a in args))[0][0])(servo[b])
        assert (j[b] - ref).abs().max() <= roundoff_tol(torch.float64, float(ref.abs().max()), ulps=4096)


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


def test_inference_module_includes_the_strain(v4_train_head):
    """The deployed FK folds the per-tendon pretension into its active-set maps like the library model."""
    spec, smap, rec = v4_train_head
    cc = strained_cc(spec, strain=True).requires_grad_(False)
    model = HardwareModel("cc", spec, smap, rec.servo_ids, cc, [cc_as_residual(make_split(rec, spec, smap, cc), cc)])
    servo_mm = 1e3 * rec.servo
    got = HardwareFK(model, torch.float64)(servo_mm)[0]
    ref = model.predict(servo_mm)[0]
    # The library residual model runs its kinematics in float32: agreement to float32 rounding at tip scale.
    assert (got - ref).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE)


def test_the_exported_fk_computes_the_stored_sigma_model_like_predict():
    """HardwareFK (what dacr_learn.export exports) gives predict's σ for a σ model of the ensemble and bend
    terms (float64), and refuses terms it cannot compute instead of silently returning another σ."""
    from dacr_learn.hardware.deploy.inference import HardwareFK

    model = synthetic_model(history=False)
    model.sigma_model = SigmaModel(("ensemble", "bend"), [1.7, 0.4], 2e-4)
    servo_mm = 1e3 * command_recording(40, 7, amplitude=4e-3).servo
    tip, sigma = model.predict(servo_mm)
    tip_fk, sigma_fk = HardwareFK(model, torch.float64)(servo_mm.double())
    # The library model runs its kinematics in float32: tips agree to float32 rounding at tip scale, and σ
    # to that times the coefficients (the members' std is a difference of such tips).
    assert torch.allclose(tip_fk, tip, rtol=0, atol=roundoff_tol(torch.float32, TIP_SCALE))
    assert torch.allclose(sigma_fk, sigma, rtol=0, atol=sigma_roundoff_tol(model, torch.float32, TIP_SCALE))
    assert not torch.allclose(sigma_fk, HardwareFK(synthetic_model(history=False), torch.float64)(servo_mm.double())[1])
    model.sigma_model = SigmaModel(("support",), [0.1], 2e-4)
    with pytest.raises(ValueError, match="unsupported: \\['support'\\]"):
        HardwareFK(model)
