"""Deploying the compositional hardware model (j): checkpoint round trip, inference modules, Jacobian, export.

Setup: every 8th row of FTDCR v4's training recording with the calibrated robot and its servo map
(the CC model fitted on those rows), and ensembles of :class:`CCCompositionalResidual` members trained
for 20 steps (enough to move the corrections off zero; training quality is not under test). A second
ensemble uses the "distal" context with torsion, a third the "segment" context, so that every input
path of the inference modules is exercised.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import ROOT, roundoff_tol

from dacr_learn import export as dexport
from dacr_learn.hardware.compositional_model import CCCompositionalResidual
from dacr_learn.hardware.deploy.checkpoint import (
    FORMAT,
    FORMAT_COMPOSITIONAL,
    HardwareModel,
    load_hardware_model,
    save_hardware_model,
)
from dacr_learn.hardware.deploy.compositional_inference import (
    CompositionalHardwareFK,
    CompositionalHardwareJacobian,
)
from dacr_learn.hardware.deploy.inference import HardwareFK
from dacr_learn.hardware.deploy.uncertainty import SigmaCalibration, SigmaModel, SupportModel
from dacr_learn.hardware.learned import cc_as_residual
from dacr_learn.hardware.study.benchmark import fit_hardware_model, load_setup
from dacr_learn.hardware.study.registry import REGISTRY, ModelInfo

pytestmark = pytest.mark.usefixtures("one_thread")
TIP_SCALE = 0.2                     # [m] magnitude of the tip coordinates (motion-capture frame)
CONFIGS = {"none": {}, "distal": {"context": "distal", "torsion": True}, "segment": {"context": "segment"}}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("v4_slice")
    rows = (ROOT / "data" / "ftdcr_v4" / "train.csv").read_text().splitlines()
    (root / "train.csv").write_text("\n".join(rows[:1] + rows[1::8]) + "\n")
    torch.set_num_threads(1)
    return load_setup(ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml", root / "train.csv", None, root)


def _model(setup, config: str = "none", members: int = 2, steps: int = 20) -> HardwareModel:
    nets = []
    for seed in range(members):
        torch.manual_seed(seed)
        member = CCCompositionalResidual(setup.train, setup.cc, steps=max(steps, 1), **CONFIGS[config])
        if steps:
            member.fit(setup.train)
        nets.append(member.eval())
    support = SupportModel(setup.train.features[..., :2], list(setup.train_rec.labels))
    return HardwareModel("cc_compositional_residual", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc,
                         nets, sigma=SigmaCalibration(1.5, 2e-4), support=support,
                         examples=1e3 * setup.train_rec.servo[:64],
                         sigma_model=SigmaModel(("ensemble", "bend"), (1.3, 0.05), 3e-4))


@pytest.fixture(scope="module")
def models(setup):
    return {config: _model(setup, config) for config in CONFIGS}


def _servo(setup, n: int = 24) -> torch.Tensor:
    """Commands [mm]: training rows spread over the recording (all three segments' patterns)."""
    servo = 1e3 * setup.train_rec.servo
    return servo[torch.linspace(0, servo.shape[0] - 1, n).long()]


def test_round_trip_is_weights_only_and_predicts_the_same(setup, models, tmp_path):
    model = models["distal"]
    path = save_hardware_model(model, tmp_path / "model.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT_COMPOSITIONAL and raw["structure"] == "compositional" and not raw["history"]
    assert raw["compositional"] == {"context": "distal", "width": 64, "depth": 2, "torsion": True}
    assert {"fk.front.norm.mean", "fk.front.norm.std", "fk.skip.weight"} <= set(raw["members"][0])
    loaded = load_hardware_model(path)
    assert loaded.compositional and not loaded.history and loaded.servo_ids == model.servo_ids
    servo = _servo(setup)
    (tip, std), (tip_l, std_l) = model.predict(servo), loaded.predict(servo)
    assert (tip_l - tip).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)
    assert (std_l - std).abs().max() <= roundoff_tol(torch.float32, float(std.max()))
    assert tip.shape == std.shape == (servo.shape[0], 3) and bool((std > 0).all())
    assert torch.equal(loaded.support_score(servo), model.support_score(servo))
    assert loaded.sigma_of().terms == ("ensemble", "bend")


def test_clarke_residual_checkpoints_keep_format_1(setup, tmp_path):
    member = cc_as_residual(setup.train, setup.cc)
    model = HardwareModel("cc", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc, [member])
    path = save_hardware_model(model, tmp_path / "cc.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT and "structure" not in raw
    assert not load_hardware_model(path).compositional


def test_bad_compositional_checkpoints_and_inputs_are_value_errors(setup, models, tmp_path):
    good = torch.load(save_hardware_model(models["none"], tmp_path / "m.pt"), weights_only=True)
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
    mixed = HardwareModel("x", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc,
                          [models["none"].members[0], cc_as_residual(setup.train, setup.cc)])
    with pytest.raises(ValueError, match="all of one kind"):
        save_hardware_model(mixed, tmp_path / "mixed.pt")
    with pytest.raises(ValueError, match=r"servo_mm: expected shape \(n, 9\)"):
        models["none"].predict(_servo(setup)[:, :4])
    fk = CompositionalHardwareFK(models["none"], torch.float64)
    with pytest.raises(ValueError, match=r"servo: expected shape \(B, 9\) \[mm\], got \(3, 4\)"):
        fk(_servo(setup)[:3, :4])
    with pytest.raises(ValueError, match="expected CCCompositionalResidual members"):
        CompositionalHardwareFK(HardwareModel("cc", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc,
                                              [cc_as_residual(setup.train, setup.cc)]))


def test_an_untrained_model_is_the_calibrated_cc_model(setup):
    """Zero output layers: the library model predicts the CC tips, and its inference module equals the
    CC model's Clarke-residual inference module (HardwareFK of a zero-residual member): another code path."""
    model = _model(setup, "distal", members=1, steps=0)
    servo = _servo(setup)
    split = model.split(servo)
    assert (model.predict(split)[0] - split.cc_tip).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)
    cc = HardwareModel("cc", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc,
                       [cc_as_residual(setup.train, setup.cc)], sigma_model=model.sigma_model)
    tip, std = CompositionalHardwareFK(model, torch.float64)(servo)
    tip_cc, std_cc = HardwareFK(cc, torch.float64)(servo)
    assert (tip - tip_cc).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE, ulps=1024)
    assert (std - std_cc).abs().max() <= roundoff_tol(torch.float64, float(std.max()))


@pytest.mark.parametrize("config", list(CONFIGS))
def test_inference_module_equals_predict(setup, models, config):
    model, servo = models[config], _servo(setup)
    tip, std = model.predict(servo)
    for dtype in (torch.float64, torch.float32):
        got_tip, got_std = CompositionalHardwareFK(model, dtype)(servo.to(dtype))
        # the library model runs its kinematics in float32: float32 rounding at tip scale either way
        assert (got_tip.double() - tip).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE, ulps=128)
        assert (got_std.double() - std).abs().max() <= roundoff_tol(torch.float32, float(std.max()), ulps=128)


@pytest.mark.parametrize("config", list(CONFIGS))
def test_jacobian_matches_autograd_in_float64(setup, models, config):
    model, servo = models[config], _servo(setup, 6)
    fk, jac = CompositionalHardwareFK(model, torch.float64), CompositionalHardwareJacobian(model, torch.float64)
    tip, j = jac(servo)
    assert j.shape == (6, 3, 9)
    assert (tip - fk(servo)[0]).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)
    for b in range(servo.shape[0]):
        ref = torch.func.jacrev(lambda s, b=b: fk(s.unsqueeze(0))[0][0])(servo[b])
        assert (j[b] - ref).abs().max() <= roundoff_tol(torch.float64, float(ref.abs().max()), ulps=1024)


def test_fk_gradcheck_in_float64(setup, models):
    fk = CompositionalHardwareFK(models["distal"], torch.float64)
    servo = _servo(setup, 4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: fk(s), (servo,), eps=1e-6, atol=1e-7)


def test_fit_hardware_model_trains_a_compositional_ensemble(setup, monkeypatch, tmp_path):
    quick = ModelInfo("cc_compositional_residual", "j", lambda c, s: CCCompositionalResidual(c.train, c.cc, steps=5),
                      "clarke", deployable=True)
    monkeypatch.setitem(REGISTRY, "cc_compositional_residual", quick)
    model = fit_hardware_model(setup, "cc_compositional_residual", [0, 1])
    assert len(model.members) == 2 and model.compositional and not model.history
    assert not any(m.training for m in model.members)
    loaded = load_hardware_model(save_hardware_model(model, tmp_path / "fitted.pt"))
    servo = _servo(setup)
    assert (loaded.predict(servo)[0] - model.predict(servo)[0]).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)


@pytest.fixture(scope="module")
def exported(setup, models, tmp_path_factory):
    out = tmp_path_factory.mktemp("hw_j")
    ckpt = save_hardware_model(models["distal"], out / "model.pt")
    return ckpt, out / "export", dexport.export_checkpoint(ckpt, out / "export", aoti=False)


def test_export_equals_the_eager_model(setup, models, exported):
    ckpt, out, meta = exported
    model = models["distal"]
    assert meta["task"] == "hardware_fk" and not meta["history"] and set(meta["modules"]) == {"fk", "jacobian"}
    assert max(meta["max_abs_deviation"].values()) <= dexport.VERIFY_TOLERANCE
    servo = _servo(setup).float()
    tip, std = dexport.load(out, "fk", checkpoint=ckpt)(servo)
    ref_tip, ref_std = model.predict(servo.double())
    assert (tip.double() - ref_tip).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE, ulps=128)
    assert (std.double() - ref_std).abs().max() <= roundoff_tol(torch.float32, float(ref_std.max()), ulps=128)
    jac = dexport.load(out, "jacobian")
    got = jac(servo)[1]
    ref = CompositionalHardwareJacobian(model, torch.float64)(servo.double())[1]
    assert (got.double() - ref).abs().max() <= roundoff_tol(torch.float32, float(ref.abs().max()), ulps=4096)
    batched = jac(servo.reshape(4, 6, 9))[1]                   # leading batch dims
    assert batched.shape == (4, 6, 3, 9)
    with pytest.raises(ValueError, match="fk input servo: expected shape"):
        dexport.load(out, "fk")(servo[:, :5])
    assert Path(out / dexport.METADATA_FILE).exists()
