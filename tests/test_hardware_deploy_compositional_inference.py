"""The compositional hardware model's inference modules (dacr_learn.hardware.deploy.compositional_inference).

Setup (fixtures ``v4_slice`` and ``compositional_models`` in tests/conftest.py): every 8th row of FTDCR v4's
training recording with the calibrated robot and its servo map (the CC model fitted on those rows), and ensembles
of :class:`CCCompositionalResidual` members trained for 20 steps (enough to move the corrections off zero; training
quality is not under test). A second ensemble uses the "distal" context with torsion, a third the "segment"
context, so that every input path of the inference modules is exercised.
"""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import (
    COMPOSITIONAL_CONFIGS,
    V4_TIP_SCALE,
    compositional_ensemble,
    sigma_roundoff_tol,
    v4_commands,
)

from dacr_learn.hardware.deploy.checkpoint import HardwareModel
from dacr_learn.hardware.deploy.compositional_inference import CompositionalHardwareFK, CompositionalHardwareJacobian
from dacr_learn.hardware.deploy.inference import HardwareFK
from dacr_learn.hardware.learned import cc_as_residual

pytestmark = pytest.mark.usefixtures("one_thread")


def test_an_untrained_model_is_the_calibrated_cc_model(v4_slice):
    """Zero output layers: the library model predicts the CC tips, and its inference module equals the
    CC model's Clarke-residual inference module (HardwareFK of a zero-residual member): another code path."""
    model = compositional_ensemble(v4_slice, "distal", members=1, steps=0)
    servo = v4_commands(v4_slice)
    split = model.split(servo)
    assert (model.predict(split)[0] - split.cc_tip).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE)
    cc = HardwareModel("cc", v4_slice.spec, v4_slice.smap, v4_slice.train_rec.servo_ids, v4_slice.cc,
                       [cc_as_residual(v4_slice.train, v4_slice.cc)], sigma_model=model.sigma_model)
    tip, std = CompositionalHardwareFK(model, torch.float64)(servo)
    tip_cc, std_cc = HardwareFK(cc, torch.float64)(servo)
    assert (tip - tip_cc).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE, ulps=1024)
    # σ comes from tip-scale quantities (the members' spread): its rounding follows the tip's scale
    assert (std - std_cc).abs().max() <= sigma_roundoff_tol(model, torch.float64, V4_TIP_SCALE, ulps=1024)


@pytest.mark.parametrize("config", list(COMPOSITIONAL_CONFIGS))
def test_inference_module_equals_predict(v4_slice, compositional_models, config):
    model, servo = compositional_models[config], v4_commands(v4_slice)
    tip, std = model.predict(servo)
    for dtype in (torch.float64, torch.float32):
        got_tip, got_std = CompositionalHardwareFK(model, dtype)(servo.to(dtype))
        # the library model runs its kinematics in float32: float32 rounding at tip scale either way, for σ too
        # (a fresh clone failed with σ's own scale: 6.3e-9 m against 128 ulps of σ.max = 0.38 mm, 5.8e-9 m)
        assert (got_tip.double() - tip).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE, ulps=128)
        assert (got_std.double() - std).abs().max() <= sigma_roundoff_tol(model, torch.float32, V4_TIP_SCALE, 128)


@pytest.mark.parametrize("config", list(COMPOSITIONAL_CONFIGS))
def test_jacobian_matches_autograd_in_float64(v4_slice, compositional_models, config):
    model, servo = compositional_models[config], v4_commands(v4_slice, 6)
    fk, jac = CompositionalHardwareFK(model, torch.float64), CompositionalHardwareJacobian(model, torch.float64)
    tip, j = jac(servo)
    assert j.shape == (6, 3, 9)
    assert (tip - fk(servo)[0]).abs().max() <= roundoff_tol(torch.float64, V4_TIP_SCALE)
    for b in range(servo.shape[0]):
        ref = torch.func.jacrev(lambda s, b=b: fk(s.unsqueeze(0))[0][0])(servo[b])
        assert (j[b] - ref).abs().max() <= roundoff_tol(torch.float64, float(ref.abs().max()), ulps=1024)


def test_fk_gradcheck_in_float64(v4_slice, compositional_models):
    fk = CompositionalHardwareFK(compositional_models["distal"], torch.float64)
    servo = v4_commands(v4_slice, 4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: fk(s), (servo,), eps=1e-6, atol=1e-7)
