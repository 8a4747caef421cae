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
