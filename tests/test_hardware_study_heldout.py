"""Held-out σ models (dacr_learn.hardware.study.heldout) on a labelled synthetic recording."""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol

pytestmark = pytest.mark.usefixtures("one_thread")


def test_sigma_models_fit_on_held_out_folds_of_a_labelled_recording(labelled_robot_dir, tmp_path):
    """On the synthetic robot whose CC model is the truth (0.1 mm noise per axis), the held-out residuals
    of the CC model are the noise: the fitted σ is ≈ 0.1 mm everywhere and the bend term negligible."""
    from dacr_learn.hardware.study.benchmark import fit_hardware_model, load_setup
    from dacr_learn.hardware.study.heldout import SIGMA_TERMS, held_out_folds, sigma_models_of

    data, robot = labelled_robot_dir
    setup = load_setup(robot, data / "train.csv", None, tmp_path)
    blocks = held_out_folds(setup, "cc", [0, 1])
    assert [(b.fold, b.preds.shape[0], len(b.tip)) for b in blocks] == [
        ("cv:single", 1, 80), ("cv:pair12", 1, 40), ("extrap:singles_to_pairs", 1, 40)]   # deterministic: one run
    assert all(bool((b.support >= 0).all()) for b in blocks)
    cal, model = sigma_models_of([b for b in blocks if b.fold.startswith("extrap:")])   # SIGMA_PROXIES
    assert model.terms == SIGMA_TERMS
    assert float(model.floor) == pytest.approx(1e-4, rel=0.35)             # 40 rows × 3 axes of 0.1 mm noise
    assert float(cal.floor) == pytest.approx(float(model.floor), rel=0.35)
    hw = fit_hardware_model(setup, "cc", [0], sigma=cal)
    servo = 1e3 * setup.train_rec.servo                                  # the whole recording [mm]
    lower, upper = hw.servo_range()                                      # the IK's box: all of it, not the examples'
    assert torch.equal(lower, servo.amin(0)) and torch.equal(upper, servo.amax(0))      # stored, not computed
    hw.sigma_model = model
    tip, sigma = hw.predict(setup.train)
    assert (tip - setup.train.cc_tip).abs().max() <= roundoff_tol(torch.float32, 0.15)   # member kinematics in float32
    assert float(sigma.max()) < 2e-4 and float(sigma.min()) >= float(model.floor) * (1 - 1e-12)


def test_the_sigma_models_held_out_rows_are_the_selection_proxies_own_fits(labelled_robot_dir, tmp_path):
    """With the proxy seeds equal to the final seeds, the σ model's held-out blocks come from the proxies' fits
    (no refit) and equal the blocks held_out_folds fits again; with other seeds there are none to reuse."""
    from dacr_learn.hardware.study.benchmark import collect_selection, load_setup, submit_selection
    from dacr_learn.hardware.study.heldout import held_out_folds, held_out_from_selection
    from dacr_learn.hardware.study.pool import TaskPool

    data, robot = labelled_robot_dir
    setup = load_setup(robot, data / "train.csv", None, tmp_path)
    selection = collect_selection(submit_selection(TaskPool(), setup, ["cc", "linear_raw"], [0]), log=lambda _: None)
    for name in ("cc", "linear_raw"):
        reused = held_out_from_selection(selection, name, [0])
        fitted = held_out_folds(setup, name, [0], ("extrap",))
        assert [b.fold for b in reused] == [b.fold for b in fitted] == ["extrap:singles_to_pairs"]
        for a, b in zip(reused, fitted, strict=True):
            for field in ("cc_tip", "tip", "rho", "support"):            # the same fold: the same inputs
                assert torch.allclose(getattr(a, field), getattr(b, field), rtol=0, atol=1e-12), field
            # the same fit, done twice: linear_raw's least squares on raw servo values is ill-conditioned, so two
            # solves differ by more than rounding at the tip scale, but far below a nanometre
            assert torch.allclose(a.preds, b.preds, rtol=0, atol=1e-9)
    assert held_out_from_selection(selection, "cc", [1]) is None                 # fitted with seed 0, not 1
    assert held_out_from_selection(selection, "mlp_raw", [0]) is None            # not scored
    scores = selection.scores["linear_raw"]
    # one held-out pattern (pair12) here: every replicate draws it, so the bootstrap has no spread
    assert scores["extrap_std"] == 0.0 and scores["extrap_per_seed"] == [scores["extrap"]]
