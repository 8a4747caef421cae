"""The generated FK (benchmarks/generated_fk.py: the eager model's own code on tensors) against
HardwareModel.predict, float64 inputs: the residual family run causally (play state passed on, the history
model) and the compositional model; σ models with terms the folded modules refuse (disagreement, support);
its torch.export program; bad inputs.

The members compute in float32 (as predict does): the generated module and predict agree to float32 rounding
at tip scale (the QP's minimiser from the enumerated active sets and from predict's iterations differ by
float64 rounding, which can move a float32 rounding of the members' inputs).
"""
from __future__ import annotations

import pytest
import torch
from conftest import load_example, roundoff_tol
from hardware_testkit import (
    TIP_SCALE,
    V4_TIP_SCALE,
    command_recording,
    sigma_roundoff_tol,
    synthetic_model,
    v4_commands,
)

from dacr_learn import export as dexport
from dacr_learn.hardware.deploy.inference import InitialState
from dacr_learn.hardware.deploy.uncertainty import SigmaModel

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
GeneratedHardwareFK = load_example("generated_fk", "benchmarks").GeneratedHardwareFK


def _causal(fk: GeneratedHardwareFK, servo_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(tips, σ) of an FK run command by command with the play state passed on (history), or in one call."""
    if not fk.history:
        return fk(servo_mm)
    state, tips, sigmas = fk.initial_state(servo_mm[:1]), [], []
    for t in range(servo_mm.shape[0]):
        tip, sigma, state = fk(servo_mm[t:t + 1], state)
        tips.append(tip)
        sigmas.append(sigma)
    return torch.cat(tips), torch.cat(sigmas)


@pytest.mark.parametrize("history", [False, True])
def test_generated_fk_equals_predict(history):
    model = synthetic_model(history)
    servo = 1e3 * command_recording(120, 5, amplitude=4e-3).servo       # partly outside the training commands
    tip, sigma = model.predict(servo)
    got_tip, got_sigma = _causal(GeneratedHardwareFK(model, F64), servo)
    tol = roundoff_tol(torch.float32, TIP_SCALE)
    assert (got_tip - tip).abs().max() <= tol
    assert (got_sigma - sigma).abs().max() <= sigma_roundoff_tol(model, torch.float32, TIP_SCALE)   # σ: tip scale
    if history:     # the play memory matters: a model started at another state predicts other tips
        fk = GeneratedHardwareFK(model, F64)
        moved = fk(servo[:1], fk.initial_state(servo[:1]) + 2e-4)[0]
        assert (moved - tip[:1]).abs().max() > 100 * tol


def test_generated_fk_equals_predict_of_the_compositional_model(v4_slice, compositional_models):
    model, servo = compositional_models["distal"], v4_commands(v4_slice)
    tip, sigma = model.predict(servo)
    got_tip, got_sigma = GeneratedHardwareFK(model, F64)(servo)
    assert (got_tip - tip).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE)
    assert (got_sigma - sigma).abs().max() <= sigma_roundoff_tol(model, torch.float32, V4_TIP_SCALE)


@pytest.mark.parametrize("terms", [("disagreement", "bend"), ("support", "ensemble")])
def test_generated_fk_computes_every_sigma_term_like_predict(terms):
    """The σ terms the folded HardwareFK refuses (it computes ensemble and bend only) come with the eager code."""
    model = synthetic_model(history=False)
    model.sigma_model = SigmaModel(terms, [1.3, 0.7], 2e-4)
    servo = 1e3 * command_recording(60, 7, amplitude=4e-3).servo
    sigma = model.predict(servo)[1]
    got = GeneratedHardwareFK(model, F64)(servo)[1]
    assert (got - sigma).abs().max() <= sigma_roundoff_tol(model, torch.float32, TIP_SCALE)
    model.support = None
    if "support" in terms:
        with pytest.raises(ValueError, match="'support' term needs the support model"):
            GeneratedHardwareFK(model)


@pytest.mark.slow
def test_the_exported_generated_program_equals_the_eager_model():
    """torch.export of the float32 module (dynamic batch; what AOTInductor compiles) against the float64 module
    run eagerly: float32 inputs, outputs and state, so float32 rounding at tip scale."""
    model = synthetic_model(history=True)
    fk, ref = GeneratedHardwareFK(model, torch.float32).eval(), GeneratedHardwareFK(model, F64)
    servo = model.examples.float()
    state = fk.initial_state(servo)
    program = dexport.export_program(fk, (servo[:2], state[:2])).module()
    init = dexport.export_program(InitialState(fk), servo[:2]).module()
    with torch.no_grad():
        got, want = program(servo, state), ref(servo.double(), state.double())
        assert (init(servo).double() - ref.initial_state(servo.double())).abs().max() <= roundoff_tol(
            torch.float32, 1e-2)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == torch.float32
        assert (g.double() - w).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)


def test_generated_fk_rejects_bad_input():
    static, history = GeneratedHardwareFK(synthetic_model(False), F64), GeneratedHardwareFK(synthetic_model(True), F64)
    servo = 1e3 * command_recording(4, 1).servo
    with pytest.raises(ValueError, match=r"servo: expected shape \(\.\.\., 8\)"):
        static(servo[:, :5])
    with pytest.raises(ValueError, match=r"servo: expected shape \(B, 8\)"):
        static(servo[0])
    with pytest.raises(ValueError, match="static model takes no state"):
        static(servo, history.initial_state(servo))
    with pytest.raises(ValueError, match="history model takes the play state"):
        history(servo)
    with pytest.raises(ValueError, match=r"state: expected shape \(4, 2, 2\)"):
        history(servo, history.initial_state(servo)[:2])
