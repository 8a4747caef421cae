"""Deploying a hardware model: checkpoint round trip, export, causal history state, Jacobian, σ, support.

A small synthetic 2-segment robot (the same kind as tests/test_hardware.py's second robot): a
CalibratedCC with non-trivial physical parameters and an ensemble of untrained residual networks
(with enlarged output weights, so that the correction matters). Training is not needed to check
that the deployed modules compute the same function as the library model.
"""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import IDS, TIP_SCALE, batch_prediction, command_recording, synthetic_model

from dacr_learn import export as dexport
from dacr_learn.hardware.deploy.checkpoint import load_hardware_model, save_hardware_model
from dacr_learn.hardware.deploy.inference import HardwareFK, HardwareJacobian
from dacr_learn.hardware.deploy.uncertainty import SigmaCalibration, ensemble_predict
from dacr_learn.hardware.learned import make_split

pytestmark = pytest.mark.usefixtures("one_thread")
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


def test_checkpoint_round_trip_loads_weights_only(tmp_path):
    model = synthetic_model(history=True)
    path = save_hardware_model(model, tmp_path / "model.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == "dacr_learn.hardware_model/3" and len(raw["members"]) == 3
    assert "clamp" not in raw and "gate_width" not in raw
    assert set(raw["members"][0]) == {"rho_std", "onehot", "net.0.weight", "net.0.bias", "net.2.weight", "net.2.bias",
                                      "net.4.weight", "net.4.bias"}
    loaded = load_hardware_model(path)
    assert loaded.servo_ids == IDS and loaded.spec == model.spec and loaded.history
    rec = command_recording(50, 9)
    assert torch.equal(batch_prediction(loaded, rec), batch_prediction(model, rec))
    rho = make_split(rec, model.spec, model.smap, model.cc).features[..., :2]
    assert torch.equal(loaded.support(rho), model.support(rho))
    assert float(loaded.sigma.scale) == 1.5 and float(loaded.sigma.floor) == 2e-4


def _format_1(blob: dict, clamp: bool = False, gate_width: float | None = None) -> dict:
    """A checkpoint as format /1 wrote it: the research options' entries and member buffers added."""
    members = [{**state, "rho_max": torch.full((2,), 3e-3), "train_clarke": torch.randn(200, 4)}
               for state in blob["members"]]
    return {**blob, "format": "dacr_learn.hardware_model/1", "clamp": clamp, "gate_width": gate_width,
            "members": members}


def test_format_1_checkpoints_load_with_the_default_options_and_refuse_research_ones(tmp_path):
    model = synthetic_model(history=True)
    blob = torch.load(save_hardware_model(model, tmp_path / "new.pt"), weights_only=True)
    torch.save(_format_1(blob), tmp_path / "old.pt")
    loaded = load_hardware_model(tmp_path / "old.pt")
    rec = command_recording(50, 9)
    assert torch.equal(batch_prediction(loaded, rec), batch_prediction(model, rec))
    for options in ({"clamp": True}, {"gate_width": 1.0}, {"gate_width": 0.0}):
        torch.save(_format_1(blob, **options), tmp_path / "research.pt")
        with pytest.raises(ValueError, match=r"research.pt: the members were fitted with the research options"):
            load_hardware_model(tmp_path / "research.pt")


def test_bad_checkpoints_are_value_errors(tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint")
    with pytest.raises(ValueError, match="notes.pt: not a weights-only hardware model checkpoint"):
        load_hardware_model(text)
    torch.save({"format": "something/2"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="expected a hardware model checkpoint of format"):
        load_hardware_model(tmp_path / "other.pt")
    good = torch.load(save_hardware_model(synthetic_model(False), tmp_path / "m.pt"), weights_only=True)
    torch.save({k: v for k, v in good.items() if k != "cc"}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match=r"lacks the entries \['cc'\]"):
        load_hardware_model(tmp_path / "partial.pt")
    good["members"][0]["net.0.weight"] = torch.zeros(3, 3)
    torch.save(good, tmp_path / "shapes.pt")
    with pytest.raises(ValueError, match="shapes.pt: the stored weights do not fit"):
        load_hardware_model(tmp_path / "shapes.pt")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("hw")
    model = synthetic_model(history=True)
    ckpt = save_hardware_model(model, out / "model.pt")
    meta = dexport.export_checkpoint(ckpt, out / "export", aoti=False)
    return model, ckpt, out / "export", meta


def test_export_of_a_hardware_checkpoint_equals_the_model(exported):
    model, ckpt, out, meta = exported
    assert meta["task"] == "hardware_fk" and meta["servo_ids"] == list(IDS)
    assert set(meta["modules"]) == {"fk", "jacobian", "initial_state"}
    assert max(meta["max_abs_deviation"].values()) <= dexport.VERIFY_TOLERANCE
    fk = dexport.load(out, "fk", checkpoint=ckpt)
    rec = command_recording(80, 11)
    servo = (1e3 * rec.servo).float()
    init = dexport.load(out, "initial_state")
    state, tips = init(servo[:1]), []
    for t in range(servo.shape[0]):                      # the controller's causal loop
        tip, std, state = fk(servo[t:t + 1], state)
        tips.append(tip)
    assert (torch.cat(tips).double() - batch_prediction(model, rec)).abs().max() <= roundoff_tol(
        torch.float32, TIP_SCALE, ulps=256)
    jac = dexport.load(out, "jacobian")
    # not the last command: the final state lies exactly at the play width from it, where J is one-sided
    # (float32 and float64 may take different sides)
    ref = HardwareJacobian(model, torch.float64)(servo[:-1].double(), state.double().expand(79, -1, -1))
    got = jac(servo[:-1], state.expand(79, -1, -1))
    assert (got[1].double() - ref[1]).abs().max() <= roundoff_tol(torch.float32, float(ref[1].abs().max()), 4096)
    with pytest.raises(ValueError, match="inputs must share their batch dims"):
        fk(servo[:3], state)
    with pytest.raises(ValueError, match="fk input state: expected shape"):
        fk(servo[:1], state[..., :1])


def test_sigma_calibration_recovers_a_known_scale_and_floor():
    g = torch.Generator().manual_seed(0)
    std = 1e-3 * torch.rand(20000, 3, generator=g, dtype=torch.float64)
    true = ((2.0 * std) ** 2 + 5e-4 ** 2).sqrt()
    residual = true * torch.randn(20000, 3, generator=g, dtype=torch.float64)
    cal = SigmaCalibration.fit(residual, std)
    assert float(cal.scale) == pytest.approx(2.0, rel=0.05)
    assert float(cal.floor) == pytest.approx(5e-4, rel=0.05)
    assert torch.equal(ensemble_predict([lambda x: x], torch.ones(2, 3))[1], torch.zeros(2, 3))


def test_support_score_is_larger_outside_the_training_box():
    model = synthetic_model(history=False)
    inside = make_split(command_recording(200, 0), model.spec, model.smap, model.cc).features[..., :2]   # training rows
    outside = inside.clone()
    coord = inside[:, 0, 0]
    outside[:, 0, 0] += (coord.max() - coord.min()) + 6 * coord.std()    # every row beyond the range by 6 std
    assert bool(model.support.outside_box(outside).all()) and not bool(model.support.outside_box(inside).any())
    score_in, score_out = model.support(inside), model.support(outside)
    assert float(score_in.max()) <= roundoff_tol(torch.float64, 10.0)      # a training row is its own neighbour
    assert float(score_out.min()) > 1.0
    between = 0.5 * (inside[:-1] + inside[1:])                             # between neighbouring training rows
    assert float(model.support(between).max()) <= 1.0


def test_the_cc_model_saves_as_a_zero_residual_member(tmp_path):
    from dacr_learn.hardware.learned import cc_as_residual

    model = synthetic_model(history=False, members=1)
    member = cc_as_residual(make_split(command_recording(200, 0), model.spec, model.smap, model.cc), model.cc)
    model.members[:] = [member]
    rec = command_recording(50, 7)
    split = make_split(rec, model.spec, model.smap, model.cc)
    with torch.no_grad():
        tip = member(split)
    assert torch.allclose(tip, split.cc_tip.double(), rtol=0, atol=roundoff_tol(torch.float32, TIP_SCALE))
    loaded = load_hardware_model(save_hardware_model(model, tmp_path / "cc.pt"))
    with torch.no_grad():
        assert torch.allclose(batch_prediction(loaded, rec), tip, rtol=0, atol=roundoff_tol(torch.float32, TIP_SCALE))
