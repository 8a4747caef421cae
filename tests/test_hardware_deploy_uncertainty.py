"""σ models of hardware tip predictions (dacr_learn.hardware.deploy.uncertainty): the heteroscedastic likelihood
fit, its features, the scores (coverage, Spearman) and the round trip of its dict through a weights-only torch file."""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import command_recording, ensemble_predict, synthetic_model
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
from dacr_learn.hardware.learned import make_split

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


# --------------------------------------------------------------------------------------------------
# The ensemble σ calibration and the support score
# --------------------------------------------------------------------------------------------------


def test_sigma_calibration_recovers_a_known_scale_and_floor():
    g = torch.Generator().manual_seed(0)
    std = 1e-3 * torch.rand(20000, 3, generator=g, dtype=torch.float64)
    true = ((2.0 * std) ** 2 + 5e-4 ** 2).sqrt()
    residual = true * torch.randn(20000, 3, generator=g, dtype=torch.float64)
    cal = SigmaCalibration.fit(residual, std)
    assert float(cal.scale) == pytest.approx(2.0, rel=0.05)
    assert float(cal.floor) == pytest.approx(5e-4, rel=0.05)
    assert torch.equal(ensemble_predict([lambda x: x], torch.ones(2, 3))[1], torch.zeros(2, 3))


def outside_box(support, rho):
    """(...) bool: some standardised Clarke coordinate of ρ (..., m, 2) beyond the training rows' range."""
    z = (rho.flatten(-2).double() - support.mean) / support.std
    return ((z < support.points.min(0).values) | (z > support.points.max(0).values)).any(-1)


def test_support_score_is_larger_outside_the_training_box():
    model = synthetic_model(history=False)
    inside = make_split(command_recording(200, 0), model.spec, model.smap, model.cc).features[..., :2]   # training rows
    outside = inside.clone()
    coord = inside[:, 0, 0]
    outside[:, 0, 0] += (coord.max() - coord.min()) + 6 * coord.std()    # every row beyond the range by 6 std
    assert bool(outside_box(model.support, outside).all()) and not bool(outside_box(model.support, inside).any())
    score_in, score_out = model.support(inside), model.support(outside)
    assert float(score_in.max()) <= roundoff_tol(torch.float64, 10.0)      # a training row is its own neighbour
    assert float(score_out.min()) > 1.0
    between = 0.5 * (inside[:-1] + inside[1:])                             # between neighbouring training rows
    assert float(model.support(between).max()) <= 1.0
