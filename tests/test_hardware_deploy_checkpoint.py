"""Hardware model checkpoints (dacr_learn.hardware.deploy.checkpoint): weights-only round trips of the Clarke-residual
ensembles (a small synthetic model, tests/hardware_testkit.py; older formats still load) and of the compositional
ones (FTDCR v4 slice), the σ model stored with them, refusals of broken or mixed checkpoints, and models that cannot
be saved yet.
"""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import (
    IDS,
    LABELLED_IDS,
    TIP_SCALE,
    V4_TIP_SCALE,
    batch_prediction,
    command_recording,
    labelled_servo_map,
    sigma_roundoff_tol,
    synthetic_model,
    v4_commands,
)

from dacr_learn.hardware.deploy.checkpoint import (
    FORMAT,
    FORMAT_COMPOSITIONAL,
    HardwareModel,
    load_hardware_model,
    save_hardware_model,
)
from dacr_learn.hardware.deploy.compositional_inference import CompositionalHardwareFK
from dacr_learn.hardware.deploy.uncertainty import TERMS, SigmaModel, sigma_terms
from dacr_learn.hardware.learned import cc_as_residual, make_split
from dacr_learn.hardware.study.registry import REGISTRY, FitContext, build_model

pytestmark = pytest.mark.usefixtures("one_thread")


# --------------------------------------------------------------------------------------------------
# Clarke-residual ensembles of the synthetic model
# --------------------------------------------------------------------------------------------------


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
    with pytest.raises(ValueError, match="notes.pt: expected a weights-only hardware model checkpoint, found"):
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


def test_model_inputs_of_servo_commands_need_no_recording():
    model = synthetic_model(history=True)
    rec = command_recording(40, 4)
    split, ref = model.split(1e3 * rec.servo), make_split(rec, model.spec, model.smap, model.cc)
    for name in ("servo", "x", "features", "cc_tip", "memory"):   # mm → m and back: rounding at each value's scale
        got, expected = getattr(split, name), getattr(ref, name)
        tol = roundoff_tol(expected.dtype, float(expected.abs().max()), ulps=1024)
        assert torch.allclose(got, expected, rtol=0, atol=tol), name
    assert split.tip.shape == (40, 3) and bool(split.tip.isnan().all())       # commands carry no measured tip


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


# --------------------------------------------------------------------------------------------------
# The compositional model (format 2) and format 1 kept for Clarke-residual ensembles
# --------------------------------------------------------------------------------------------------


def test_round_trip_is_weights_only_and_predicts_the_same(v4_slice, compositional_models, tmp_path):
    model = compositional_models["distal"]
    path = save_hardware_model(model, tmp_path / "model.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT_COMPOSITIONAL and raw["structure"] == "compositional" and not raw["history"]
    assert raw["compositional"] == {"context": "distal", "width": 64, "depth": 2, "torsion": True}
    assert {"fk.front.norm.mean", "fk.front.norm.std", "fk.skip.weight"} <= set(raw["members"][0])
    loaded = load_hardware_model(path)
    assert loaded.compositional and not loaded.history and loaded.servo_ids == model.servo_ids
    servo = v4_commands(v4_slice)
    (tip, std), (tip_l, std_l) = model.predict(servo), loaded.predict(servo)
    assert (tip_l - tip).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE)
    assert (std_l - std).abs().max() <= sigma_roundoff_tol(model, torch.float32, V4_TIP_SCALE)
    assert tip.shape == std.shape == (servo.shape[0], 3) and bool((std > 0).all())
    assert torch.equal(loaded.support_score(servo), model.support_score(servo))
    assert loaded.sigma_of().terms == ("ensemble", "bend")


def test_clarke_residual_checkpoints_are_not_compositional(v4_slice, tmp_path):
    member = cc_as_residual(v4_slice.train, v4_slice.cc)
    model = HardwareModel("cc", v4_slice.spec, v4_slice.smap, v4_slice.train_rec.servo_ids, v4_slice.cc, [member])
    path = save_hardware_model(model, tmp_path / "cc.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT and "structure" not in raw
    assert not load_hardware_model(path).compositional


def test_bad_compositional_checkpoints_and_inputs_are_value_errors(v4_slice, compositional_models, tmp_path):
    good = torch.load(save_hardware_model(compositional_models["none"], tmp_path / "m.pt"), weights_only=True)
    torch.save({k: v for k, v in good.items() if k != "compositional"}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match=r"lacks the entries \['compositional'\]"):
        load_hardware_model(tmp_path / "partial.pt")
    for bad in ({"structure": "clarke_residual"}, {"history": True}):        # a /2 file that is not compositional
        torch.save({**good, **bad}, tmp_path / "structure.pt")
        with pytest.raises(ValueError, match="structure: expected 'compositional' without history"):
            load_hardware_model(tmp_path / "structure.pt")
    torch.save({**good, "compositional": {**good["compositional"], "width": 32}}, tmp_path / "shapes.pt")
    with pytest.raises(ValueError, match="shapes.pt: the stored weights do not fit"):
        load_hardware_model(tmp_path / "shapes.pt")
    mixed = HardwareModel("x", v4_slice.spec, v4_slice.smap, v4_slice.train_rec.servo_ids, v4_slice.cc,
                          [compositional_models["none"].members[0], cc_as_residual(v4_slice.train, v4_slice.cc)])
    with pytest.raises(ValueError, match="all of one kind"):
        save_hardware_model(mixed, tmp_path / "mixed.pt")
    with pytest.raises(ValueError, match=r"servo_mm: expected shape \(n, 9\)"):
        compositional_models["none"].predict(v4_commands(v4_slice)[:, :4])
    fk = CompositionalHardwareFK(compositional_models["none"], torch.float64)
    with pytest.raises(ValueError, match=r"servo: expected shape \(B, 9\) \[mm\], got \(3, 4\)"):
        fk(v4_commands(v4_slice)[:3, :4])
    with pytest.raises(ValueError, match="expected CCCompositionalResidual members"):
        CompositionalHardwareFK(HardwareModel("cc", v4_slice.spec, v4_slice.smap, v4_slice.train_rec.servo_ids,
                                              v4_slice.cc, [cc_as_residual(v4_slice.train, v4_slice.cc)]))


def test_history_variant_is_scored_but_cannot_be_saved_yet(compositional_split, tmp_path):
    from dacr_learn.hardware.deploy.checkpoint import HardwareModel, save_hardware_model

    cc, split = compositional_split
    info = REGISTRY["cc_compositional_history"]
    assert info.clarke_space and not info.static and not info.deployable
    member = build_model("cc_compositional_history", FitContext(cc, labelled_servo_map(cc.spec), LABELLED_IDS, split),
                         0)
    model = HardwareModel("cc_compositional_history", cc.spec, labelled_servo_map(cc.spec), LABELLED_IDS, cc, [member])
    with pytest.raises(ValueError, match="history inputs .* cannot be saved yet"):
        save_hardware_model(model, tmp_path / "model.pt")


# --------------------------------------------------------------------------------------------------
# The σ model
# --------------------------------------------------------------------------------------------------


def test_checkpoint_stores_the_sigma_model_and_predict_exposes_sigma(tmp_path):
    from hardware_testkit import command_recording, synthetic_model

    from dacr_learn.hardware.deploy.checkpoint import load_hardware_model, save_hardware_model

    model = synthetic_model(history=True)
    model.sigma_model = SigmaModel(TERMS, [1.2, 0.3, 2e-4, 0.1], 3e-4)
    servo_mm = 1e3 * command_recording(50, 5, amplitude=4e-3).servo
    tip, sigma = model.predict(servo_mm)
    loaded = load_hardware_model(save_hardware_model(model, tmp_path / "model.pt"))
    assert loaded.sigma_model.to_dict() == model.sigma_model.to_dict()
    tip2, sigma2 = loaded.predict(servo_mm)
    assert torch.allclose(tip2, tip, rtol=0, atol=1e-12) and torch.allclose(sigma2, sigma, rtol=1e-12, atol=0)
    # σ is the σ model of the features: floor ≤ σ, and σ² − σ₀² the sum of the terms' squares
    split = model.split(servo_mm)
    preds = torch.stack([m(split) for m in model.members]).detach()
    feats = sigma_terms(preds, split.cc_tip, split.features[..., :2], model.support.distance(split.features[..., :2]))
    assert torch.allclose(sigma, model.sigma_model(feats), rtol=1e-12, atol=0)
    assert bool((sigma >= 3e-4).all())
    assert torch.allclose(loaded.support_score(servo_mm), model.support(split.features[..., :2]), rtol=1e-12, atol=0)
    model.sigma_model = None                                   # without one: the calibrated ensemble std
    assert torch.allclose(model.predict(split)[1], model.sigma(preds.std(0)), rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match=r"servo_mm: expected shape \(n, 8\)"):
        model.predict(servo_mm[:, :5])


def test_servo_range_is_the_stored_recorded_range_else_the_examples(tmp_path):
    """``servo_range``: info["servo_range_mm"] (the whole training recording, stored since 2026-11-28) through a
    weights-only round trip; a file without it gets the range of its example commands; neither: a ValueError."""
    model = synthetic_model(history=False, members=1)
    old = model.servo_range()                                             # a file saved before the entry existed
    assert torch.equal(old[0], model.examples.amin(0)) and torch.equal(old[1], model.examples.amax(0))
    recorded = 1e3 * command_recording(200, 0).servo
    model.info["servo_range_mm"] = {"lower": recorded.amin(0).tolist(), "upper": recorded.amax(0).tolist()}
    lower, upper = load_hardware_model(save_hardware_model(model, tmp_path / "m.pt")).servo_range()
    assert lower.dtype == torch.float64 and torch.equal(lower, recorded.amin(0))        # stored values, not computed
    assert torch.equal(upper, recorded.amax(0))
    model.info["servo_range_mm"] = {"lower": [0.0] * 3, "upper": [1.0] * 3}
    with pytest.raises(ValueError, match="servo_range_mm.*8 values"):
        model.servo_range()
    model.info.pop("servo_range_mm")
    model.examples = None
    with pytest.raises(ValueError, match="recorded servo range is unknown"):
        model.servo_range()
