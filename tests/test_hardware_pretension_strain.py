"""Calibrated CC model with a pretension that grows with the tendon path length (``pretension_strain``).

Tendon i's pretension stretch is p_i = p + s·(L_i/L̄ − 1). References: the model without the option
fed with commands shifted by s·(L_i/L̄ − 1) (another code path), the option off / s = 0 being the model
before, a state-dict round trip, gradcheck in s, and the deployed fast path (HardwareFK) against
the library model.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
import torch
from conftest import roundoff_tol

from dacr_learn.hardware.ccmodel import CalibratedCC, fit_cc
from dacr_learn.hardware.deploy.checkpoint import HardwareModel
from dacr_learn.hardware.deploy.inference import HardwareFK
from dacr_learn.hardware.learned import cc_as_residual, make_split
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.study.benchmark import resolve_robot

ROOT = Path(__file__).resolve().parents[1]
TIP_SCALE = 0.2                                   # [m] magnitude of the tip coordinates
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def v4():
    """(spec, servo map, the first 240 rows of FTDCR v4's train.csv)."""
    spec, smap, _ = resolve_robot(ROOT / "configs/robots/ftdcr_v4_calibrated.yaml", None, None,
                                  Path(tempfile.mkdtemp()), "mm")
    rec = load_recording(ROOT / "data/ftdcr_v4/train.csv", spec)
    return spec, smap, rec.select(torch.arange(len(rec)) < 240)


def _model(spec, strain: bool, p: float = 3e-4, s: float = 5e-4) -> CalibratedCC:
    cc = CalibratedCC(spec, compliance=1e-6, pretension_strain=strain)
    with torch.no_grad():
        cc.encoder.log_radius_scale.copy_(torch.tensor([0.05, -0.03, 0.02]))
        cc.encoder.rotation.copy_(torch.tensor([0.02, -0.04, 0.03]))
        cc.encoder.pretension.fill_(p)
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005]))
        cc.tip_offset.fill_(8e-3)
        if strain:
            cc.encoder.pretension_strain.fill_(s)
    return cc


def _x(v4):
    spec, smap, rec = v4
    return smap.displacements(spec, rec)


def test_without_strain_every_tendon_has_the_common_pretension(v4):
    cc = _model(v4[0], strain=False)
    assert "encoder.pretension_strain" not in cc.state_dict() and "pretension_per_segment_mm" not in cc.report()
    assert torch.equal(cc.encoder.tendon_pretension(), torch.full((9,), 3e-4, dtype=torch.float64))


def test_strain_is_a_path_length_proportional_shift_of_the_commands(v4):
    spec, x = v4[0], _x(v4)
    strained, plain = _model(spec, strain=True), _model(spec, strain=False)
    path = plain.encoder.path_length
    shift = 5e-4 * (path / path.mean() - 1)
    with torch.no_grad():
        got, ref = strained(x), plain(x + shift)
    assert (got - ref).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)
    assert (got - plain(x)).abs().max() > 1e-4          # the option changes the model (0.1 mm)


def test_zero_strain_is_the_model_without_it(v4):
    spec, x = v4[0], _x(v4)
    with torch.no_grad():
        diff = (_model(spec, strain=True, s=0.0)(x) - _model(spec, strain=False)(x)).abs().max()
    assert diff <= roundoff_tol(torch.float64, TIP_SCALE)


def test_pure_strain_stretches_each_tendon_in_proportion_to_its_length(v4):
    enc = _model(v4[0], strain=True, p=4e-4, s=4e-4).encoder
    ratio = enc.tendon_pretension() / enc.path_length
    assert (ratio - ratio.mean()).abs().max() <= roundoff_tol(torch.float64, ratio.abs().max().item())
    assert len(set(enc.path_length.tolist())) == 3      # three path lengths on a 3-segment robot: a real test


def test_state_dict_round_trip_keeps_the_strain(v4):
    spec, x = v4[0], _x(v4)
    cc = _model(spec, strain=True)
    again = CalibratedCC.from_state_dict(spec, cc.state_dict())
    assert again.encoder.strain and "pretension_per_segment_mm" in again.report()
    with torch.no_grad():
        assert (again(x) - cc(x)).abs().max() <= roundoff_tol(torch.float64, TIP_SCALE)


def test_gradcheck_in_the_strain(v4):
    spec, x = v4[0], _x(v4)[:20]
    cc = _model(spec, strain=True)
    names = ["encoder.pretension_strain"]
    params = {n: p.detach().clone() for n, p in cc.named_parameters()}

    def tip(s):
        return torch.func.functional_call(cc, {**params, names[0]: s}, (x,))

    assert torch.autograd.gradcheck(tip, (params[names[0]].clone().requires_grad_(True),), eps=1e-7, atol=1e-6)


def test_fit_recovers_the_strain(v4):
    spec, x = v4[0], _x(v4)
    truth = _model(spec, strain=True, s=6e-4)
    with torch.no_grad():
        tip = truth(x)
    cc = CalibratedCC(spec, pretension_strain=True)
    fit = fit_cc(cc, x, tip)
    assert fit["rms_m"] < 1e-4                           # 0.1 mm on a 0.2 m robot
    assert abs(cc.encoder.pretension_strain.item() - 6e-4) < 1e-4


def test_inference_module_includes_the_strain(v4):
    """The deployed FK folds the per-tendon pretension into its active-set maps like the library model."""
    spec, smap, rec = v4
    cc = _model(spec, strain=True).requires_grad_(False)
    model = HardwareModel("cc", spec, smap, rec.servo_ids, cc, [cc_as_residual(make_split(rec, spec, smap, cc), cc)])
    servo_mm = 1e3 * rec.servo
    got = HardwareFK(model, torch.float64)(servo_mm)[0]
    ref = model.predict(servo_mm)[0]
    # The library residual model runs its kinematics in float32: agreement to float32 rounding at tip scale.
    assert (got - ref).abs().max() <= roundoff_tol(torch.float32, TIP_SCALE)


def test_cc_variant_is_chosen_by_the_singles_to_pairs_score_of_the_cc_model(v4):
    from dacr_learn.hardware.study.selection import CC_VARIANTS, choose_cc_variant, fold_rmse, make_folds, proxy_masks

    spec, smap, _ = v4
    rec = load_recording(ROOT / "data/ftdcr_v4/train.csv", spec)
    chosen, scores = choose_cc_variant(rec, spec, smap)
    assert set(scores) == set(CC_VARIANTS) and chosen == min(scores, key=scores.get)
    masks = proxy_masks(rec.labels, ("extrap",))["extrap"]
    fold, = make_folds(rec, spec, smap, masks, CC_VARIANTS["strain"])
    assert fold.ctx.cc.encoder.strain                          # the folds are built with the variant's CC model
    assert abs(fold_rmse("cc", fold, 0) - scores["strain"]) <= 1e-3   # same fit, same score [mm] (rounded to 1e-4)
    with pytest.raises(ValueError, match="cc variants: expected one or more of"):
        choose_cc_variant(rec, spec, smap, ("stiff",))


def test_load_setup_records_the_cc_variant_and_refuses_an_unknown_one(tmp_path):
    from dacr_learn.hardware.study.benchmark import load_setup

    robot, data = ROOT / "configs/robots/ftdcr_v4_calibrated.yaml", ROOT / "data/ftdcr_v4"
    setup = load_setup(robot, data / "train.csv", None, tmp_path, cc_variant="strain")
    assert setup.cc.encoder.strain and setup.cc_options == {"pretension_strain": True}
    assert setup.cc_fit["variant"] == {"requested": "strain", "chosen": "strain"}
    with pytest.raises(ValueError, match="cc_variant: expected 'auto' or one of"):
        load_setup(robot, data / "train.csv", None, tmp_path, cc_variant="stiff")
