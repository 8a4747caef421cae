"""σ models of hardware tip predictions: the heteroscedastic likelihood fit, its features, the scores
(coverage, Spearman) and the round trip through a weights-only checkpoint."""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import spearmanr

from dacr_learn.hardware.deploy.uncertainty import (
    TERMS,
    SigmaCalibration,
    SigmaModel,
    coverage,
    sigma_terms,
    spearman,
)

pytestmark = pytest.mark.usefixtures("one_thread")
N = 20000


def _features(g: torch.Generator) -> dict[str, torch.Tensor]:
    return {"ensemble": 1e-3 * torch.rand(N, 3, generator=g, dtype=torch.float64),
            "disagreement": 2e-3 * torch.rand(N, 3, generator=g, dtype=torch.float64),
            "support": 3.0 * torch.rand(N, 1, generator=g, dtype=torch.float64),
            "bend": 4e-3 * torch.rand(N, 1, generator=g, dtype=torch.float64)}


def test_fit_recovers_known_coefficients_and_floor():
    g = torch.Generator().manual_seed(0)
    feats = _features(g)
    true = SigmaModel(TERMS, [1.5, 0.8, 1e-3, 0.5], 4e-4)
    residual = true(feats) * torch.randn(N, 3, generator=g, dtype=torch.float64)
    fitted = SigmaModel.fit(TERMS, feats, residual)
    # 3·N samples: the maximum-likelihood estimates lie within a few percent of the truth.
    assert fitted.coefficients.tolist() == pytest.approx(true.coefficients.tolist(), rel=0.1)
    assert float(fitted.floor) == pytest.approx(4e-4, rel=0.1)
    assert coverage(residual, fitted(feats)) == pytest.approx(0.9545, abs=0.01)   # P(|z| ≤ 2) of a Gaussian


def test_a_useless_term_gets_a_small_coefficient():
    g = torch.Generator().manual_seed(1)
    feats = _features(g)
    residual = SigmaModel(("bend",), [0.5], 1e-4)(feats) * torch.randn(N, 3, generator=g, dtype=torch.float64)
    fitted = SigmaModel.fit(("bend", "support"), feats, residual)
    contribution = fitted.coefficients * torch.stack([feats[t].pow(2).mean().sqrt() for t in fitted.terms])
    assert float(contribution[1]) < 0.1 * float(contribution[0])


def test_ensemble_only_model_is_the_sigma_calibration():
    g = torch.Generator().manual_seed(2)
    std = 1e-3 * torch.rand(5000, 3, generator=g, dtype=torch.float64)
    residual = ((2.0 * std) ** 2 + 5e-4 ** 2).sqrt() * torch.randn(5000, 3, generator=g, dtype=torch.float64)
    cal = SigmaCalibration.fit(residual, std)
    model = SigmaModel(("ensemble",), [float(cal.scale)], float(cal.floor))
    assert torch.allclose(model({"ensemble": std}), cal(std), rtol=1e-12, atol=0)


def test_sigma_terms_values():
    g = torch.Generator().manual_seed(3)
    preds = torch.randn(4, 7, 3, generator=g, dtype=torch.float64)
    cc = torch.randn(7, 3, generator=g, dtype=torch.float64)
    rho = torch.randn(7, 3, 2, generator=g, dtype=torch.float64)
    d = torch.rand(7, generator=g, dtype=torch.float64)
    f = sigma_terms(preds, cc, rho, d)
    assert torch.allclose(f["ensemble"], preds.std(0))
    assert torch.allclose(f["disagreement"], (preds.mean(0) - cc).abs())
    assert torch.allclose(f["bend"][:, 0], rho.reshape(7, 6).norm(dim=-1))
    assert torch.equal(f["support"][:, 0], d)
    assert torch.equal(sigma_terms(preds[:1], cc, rho, d)["ensemble"], torch.zeros(7, 3, dtype=torch.float64))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(-10**6, 10**6), min_size=3, max_size=40, unique=True), st.integers(0, 2**31 - 1))
def test_spearman_matches_scipy(values, seed):
    a = torch.tensor(values, dtype=torch.float64) / 1e3
    b = a + torch.randn(len(values), generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * a.std()
    if len(set(b.tolist())) < len(values):
        return
    assert spearman(a, b) == pytest.approx(spearmanr(a.numpy(), b.numpy()).statistic, abs=1e-12)
    assert spearman(a, a**3) == pytest.approx(1.0, abs=1e-12)          # rank correlation ignores monotone maps


def test_checkpoint_dict_round_trip_is_weights_only(tmp_path):
    model = SigmaModel(("ensemble", "bend"), [1.3, 0.2], 3e-4)
    torch.save({"sigma_model": model.to_dict()}, tmp_path / "s.pt")
    back = SigmaModel.from_dict(torch.load(tmp_path / "s.pt", weights_only=True)["sigma_model"])
    feats = _features(torch.Generator().manual_seed(4))
    assert back.terms == model.terms
    assert torch.equal(back(feats), model(feats))


def test_bad_input_is_named():
    feats = _features(torch.Generator().manual_seed(5))
    with pytest.raises(ValueError, match="distinct terms of"):
        SigmaModel(("ensemble", "wind"), [1.0, 1.0], 0.0)
    with pytest.raises(ValueError, match="one coefficient each"):
        SigmaModel(("ensemble",), [1.0, 2.0], 0.0)
    with pytest.raises(ValueError, match="missing"):
        SigmaModel(("bend",), [1.0], 0.0)({"ensemble": feats["ensemble"]})
    with pytest.raises(ValueError, match="rows like residual"):
        SigmaModel.fit(("bend",), {"bend": feats["bend"][:10]}, torch.zeros(20, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"preds: expected shape \(K, 5, 3\)"):
        sigma_terms(torch.zeros(2, 4, 3), torch.zeros(5, 3), torch.zeros(5, 2, 2), torch.zeros(5))
    with pytest.raises(ValueError, match="residual/sigma"):
        coverage(torch.zeros(4, 3), torch.zeros(4, 1))
    with pytest.raises(ValueError, match="equal shapes"):
        spearman(torch.zeros(4), torch.zeros(5))


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


def test_sigma_models_fit_on_held_out_folds_of_a_labelled_recording(labelled_robot_dir, tmp_path):
    """On the synthetic robot whose CC model is the truth (0.1 mm noise per axis), the held-out residuals
    of the CC model are the noise: the fitted σ is ≈ 0.1 mm everywhere and the bend term negligible."""
    from dacr_learn.hardware.study.benchmark import fit_hardware_model, load_setup
    from dacr_learn.hardware.study.heldout import SIGMA_TERMS, held_out_folds, sigma_models

    data, robot = labelled_robot_dir
    setup = load_setup(robot, data / "train.csv", None, tmp_path)
    blocks = held_out_folds(setup, "cc", [0, 1])
    assert [(b.fold, b.preds.shape[0], len(b.tip)) for b in blocks] == [
        ("cv:single", 1, 80), ("cv:pair12", 1, 40), ("extrap:singles_to_pairs", 1, 40)]   # deterministic: one run
    assert all(bool((b.support >= 0).all()) for b in blocks)
    cal, model = sigma_models(setup, "cc", [0, 1])
    assert model.terms == SIGMA_TERMS
    assert float(model.floor) == pytest.approx(1e-4, rel=0.35)             # 40 rows × 3 axes of 0.1 mm noise
    assert float(cal.floor) == pytest.approx(float(model.floor), rel=0.35)
    hw = fit_hardware_model(setup, "cc", [0], sigma=cal)
    hw.sigma_model = model
    tip, sigma = hw.predict(setup.train)
    assert (tip - setup.train.cc_tip).abs().max() <= roundoff_tol(torch.float32, 0.15)   # member kinematics in float32
    assert float(sigma.max()) < 2e-4 and float(sigma.min()) >= float(model.floor) * (1 - 1e-12)


def test_the_exported_fk_computes_the_stored_sigma_model_like_predict():
    """HardwareFK (what dacr_learn.export exports) gives predict's σ for a σ model of the ensemble and bend
    terms (float64), and refuses terms it cannot compute instead of silently returning another σ."""
    from hardware_testkit import TIP_SCALE, command_recording, synthetic_model

    from dacr_learn.hardware.deploy.inference import HardwareFK

    model = synthetic_model(history=False)
    model.sigma_model = SigmaModel(("ensemble", "bend"), [1.7, 0.4], 2e-4)
    servo_mm = 1e3 * command_recording(40, 7, amplitude=4e-3).servo
    tip, sigma = model.predict(servo_mm)
    tip_fk, sigma_fk = HardwareFK(model, torch.float64)(servo_mm.double())
    # The library model runs its kinematics in float32: tips agree to float32 rounding at tip scale, and σ
    # to that times the ensemble coefficient (the members' std is a difference of such tips).
    tol = roundoff_tol(torch.float32, TIP_SCALE)
    assert torch.allclose(tip_fk, tip, rtol=0, atol=tol)
    assert torch.allclose(sigma_fk, sigma, rtol=0, atol=2 * tol)
    assert not torch.allclose(sigma_fk, HardwareFK(synthetic_model(history=False), torch.float64)(servo_mm.double())[1])
    model.sigma_model = SigmaModel(("support",), [0.1], 2e-4)
    with pytest.raises(ValueError, match="unsupported: \\['support'\\]"):
        HardwareFK(model)
