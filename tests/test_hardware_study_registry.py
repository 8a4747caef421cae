"""The model registry (dacr_learn.hardware.study.registry): names, flags, what builds and what ships."""
from __future__ import annotations

import pytest
import torch
from hardware_testkit import LABELLED_IDS, labelled_servo_map

from dacr_learn.hardware.compositional_model import CCCompositionalResidual
from dacr_learn.hardware.study.registry import MODELS, REGISTRY, FitContext, build_model, model_info

pytestmark = pytest.mark.usefixtures("one_thread")
NAME = "cc_compositional_residual"


def test_registry_has_unique_names_and_flags():
    assert len(set(MODELS)) == len(MODELS) == 14 and all(REGISTRY[m].name == m for m in MODELS)
    assert {m for m in MODELS if REGISTRY[m].deterministic} == {"linear_raw", "cc", "cosserat"}
    assert {m for m in MODELS if REGISTRY[m].deployable} == {"cc", "cc_clarke_residual", "cc_clarke_residual_history",
                                                             "cc_compositional_residual", "cc_clarke_residual_cosserat",
                                                             "cc_clarke_residual_history_cosserat"}
    assert [m for m in MODELS if not REGISTRY[m].static] == ["cc_clarke_residual_history", "cc_compositional_history",
                                                             "cc_clarke_residual_history_cosserat"]
    history = model_info("cc_compositional_history")
    assert history.clarke_space and not history.deployable
    assert not model_info("mlp_raw").clarke_space and model_info("pretrained_clarke").clarke_space
    with pytest.raises(ValueError, match="expected one of"):
        model_info("mlp")
    with pytest.raises(ValueError, match="expected one of"):      # no ad-hoc variants: only what can ship is scored
        model_info(REGISTRY["cc"])


def test_registered_with_clarke_inputs(compositional_split):
    cc, split = compositional_split
    info = REGISTRY[NAME]
    assert info.clarke_space and info.static and not info.deterministic
    ctx = FitContext(cc, labelled_servo_map(cc.spec), LABELLED_IDS, split)
    assert isinstance(build_model(NAME, ctx, 0), CCCompositionalResidual)


def test_models_are_built_from_shapes_and_fit_sets_their_statistics(compositional_split):
    """No training data in a constructor: every registered model builds from a context without a training split;
    the data-dependent statistics are set by fit (its first step, fit_normalization)."""
    cc, split = compositional_split
    shapes_only = FitContext(cc, labelled_servo_map(cc.spec), LABELLED_IDS, None)
    models = {name: build_model(name, shapes_only, 0) for name in MODELS}
    tip_mlp, residual, compositional = models["mlp_clarke"], models["cc_clarke_residual"], models[NAME]
    assert not tip_mlp.norm.mean.any() and float(residual.rho_std) == 1.0
    for model in (tip_mlp, residual, compositional):
        model.fit_normalization(split)
    assert torch.equal(tip_mlp.norm.mean, split.clarke.mean(0)) and torch.equal(tip_mlp.norm.std, split.clarke.std(0))
    assert torch.equal(tip_mlp.tip_mean, split.tip.float().mean(0))
    assert torch.equal(residual.rho_std, split.features[..., :2].float().std())
    features = compositional.segment_features(split).flatten(0, 1).double()
    assert torch.allclose(compositional.fk.front.norm.mean, features.mean(0).float(), rtol=0, atol=0)
