"""The compositional hardware model: calibrated CC segment transforms × learned per-segment twists.

A synthetic recording of a small two-segment robot (the calibrated CC model at its nominal
parameters, :func:`~dacr_learn.hardware.learned.synthetic_split`; fixture ``compositional_split`` in
tests/conftest.py) stands in for hardware data.
"""
from __future__ import annotations

import pytest
import torch

from dacr_learn.hardware.compositional_model import TWIST_SCALE, CCCompositionalResidual
from dacr_learn.hardware.learned import Split
from dacr_learn.kinematics import segment_poses

pytestmark = pytest.mark.usefixtures("one_thread")


def _built(split: Split, cc, **options) -> CCCompositionalResidual:
    """The model built from its shape, its feature standardiser fitted on ``split`` (the first step of fit)."""
    model = CCCompositionalResidual(cc, **options)
    model.fit_normalization(split)
    return model


def _randomised(model: CCCompositionalResidual, seed: int = 1) -> CCCompositionalResidual:
    """The model with every network weight drawn at random (the output layers start at zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.fk.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return model


def test_untrained_model_is_the_calibrated_cc_model(compositional_split):
    cc, split = compositional_split
    model = CCCompositionalResidual(cc)
    with torch.no_grad():
        tip, ends = model(split), model.segment_ends(split)
    assert tip.shape == (64, 3) and tip.dtype == torch.float64 and ends.shape == (64, 2, 4, 4)
    scale = float(cc.spec.total_length)
    assert torch.allclose(tip, split.cc_tip, atol=64 * torch.finfo(torch.float32).eps * scale)


def test_composition_matches_an_independent_product_of_exponentials(compositional_split):
    """Segment ends = ∏_k T_k^CC · expm(ξ_k^) with torch.linalg.matrix_exp, float64, to round-off."""
    cc, split = compositional_split
    model = _randomised(_built(split, cc, context="distal", torsion=True)).double()
    with torch.no_grad():
        ends = model.segment_ends(split)
        fk, front = model.fk, model.fk.front
        z = front.with_context(front.norm(model.segment_features(split)))
        xi = (fk.net(z) + fk.skip(z)) * TWIST_SCALE
        v, w = xi[..., :3] * fk.length_scale.unsqueeze(-1), xi[..., 3:]
        hat = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
        hat[..., 0, 1], hat[..., 0, 2], hat[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
        hat[..., 1, 0], hat[..., 2, 0], hat[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
        hat[..., :3, 3] = v
        poses = segment_poses(cc.spec, split.features) @ torch.linalg.matrix_exp(hat)
        expected = torch.stack([poses[:, 0], poses[:, 0] @ poses[:, 1]], 1)
    assert w.abs().max() > 1e-2                      # the corrections are not trivially the identity
    assert torch.allclose(ends, expected, atol=1e3 * torch.finfo(torch.float64).eps)


def test_without_torsion_the_corrections_do_not_roll_about_the_segment_axis(compositional_split):
    """torsion=False: ω_z = 0, so each correction's rotation axis lies in the end frame's xy plane
    (the skew part of R, sin φ · n^, has n_z = 0: R_10 = R_01)."""
    cc, split = compositional_split
    rolled = _randomised(_built(split, cc, torsion=True)).double()
    plain = _randomised(_built(split, cc, torsion=False)).double()
    with torch.no_grad():
        r_plain, r_rolled = plain.corrections(split)[..., :3, :3], rolled.corrections(split)[..., :3, :3]
    tol = 64 * torch.finfo(torch.float64).eps
    assert torch.allclose(r_plain[..., 1, 0], r_plain[..., 0, 1], atol=tol)
    assert (r_rolled[..., 1, 0] - r_rolled[..., 0, 1]).abs().max() > 1e-3


def test_fit_reduces_the_training_error_of_a_non_cc_robot(compositional_split):
    cc, split = compositional_split
    bend = split.features[..., :2].norm(dim=-1).sum(-1, keepdim=True) / 5e-3     # total bend [rad]
    target = Split(split.servo, split.x, split.features, split.cc_tip,
                   split.cc_tip + 4e-3 * bend * torch.tensor([1.0, -0.5, 0.3], dtype=torch.float64),
                   split.memory)
    torch.manual_seed(0)
    model = CCCompositionalResidual(cc, steps=25, lr=2e-2)
    rmse = lambda: float((model(target) - target.tip).pow(2).sum(-1).mean().sqrt())  # noqa: E731
    with torch.no_grad():
        before = rmse()
    model.fit(target)
    with torch.no_grad():
        assert rmse() < 0.5 * before
    assert not any(p.requires_grad for p in cc.parameters())


def test_gradients_wrt_the_features_and_the_weights(compositional_split):
    cc, split = compositional_split
    rows = split.rows(torch.arange(4))
    model = _randomised(_built(rows, cc, context="segment")).double()

    def tip(features):
        return model(Split(rows.servo, rows.x, features, rows.cc_tip, rows.tip, rows.memory))

    features = rows.features.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(tip, (features,), eps=1e-7, atol=1e-6)
    model.objective(rows).backward()
    grads = [p.grad for p in model.fk.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.abs().max() > 0 for g in grads)


def test_weight_decay_adds_the_squared_weights(compositional_split):
    cc, split = compositional_split
    plain = _randomised(_built(split, cc, weight_decay=0.0))
    decayed = _randomised(_built(split, cc, weight_decay=0.5))
    with torch.no_grad():
        squares = sum(float(m.weight.pow(2).sum()) for m in decayed.fk.modules() if isinstance(m, torch.nn.Linear))
        diff = float(decayed.objective(split) - plain.objective(split))
    assert diff == pytest.approx(0.5 * squares, rel=1e-5)


def test_bad_input_raises(compositional_split):
    cc, split = compositional_split
    with pytest.raises(ValueError, match="weight_decay"):
        CCCompositionalResidual(cc, weight_decay=-1.0)
    with pytest.raises(ValueError, match="context"):
        CCCompositionalResidual(cc, context="proximal")
    model = CCCompositionalResidual(cc)
    with pytest.raises(ValueError, match="hardware Split"):
        model(split.features)
    short = Split(split.servo, split.x, split.features[:, :1], split.cc_tip, split.tip, split.memory)
    with pytest.raises(ValueError, match="features"):
        model(short)


def _with_memory(split: Split, seed: int = 2) -> Split:
    """The split with a random play memory (n, m, 2) in the unit disc (synthetic splits carry zeros)."""
    g = torch.Generator().manual_seed(seed)
    memory = torch.rand(split.memory.shape, generator=g, dtype=torch.float64) * 2 - 1
    return Split(split.servo, split.x, split.features, split.cc_tip, split.tip, memory / 2)


def test_history_variant_feeds_each_segment_its_own_memory(compositional_split):
    """history=True: untrained it is the CC model whatever the memory; trained weights make each segment's
    correction depend on its own memory (segment k's correction moves only when memory[:, k] does)."""
    cc, split = compositional_split
    moved = _with_memory(split)
    untrained = CCCompositionalResidual(cc, history=True)
    assert untrained.history and not CCCompositionalResidual(cc).history
    with torch.no_grad():
        assert torch.allclose(untrained(moved), split.cc_tip, atol=64 * torch.finfo(torch.float32).eps * 0.15)
    model = _randomised(_built(split, cc, history=True)).double()
    assert model.fk.skip.in_features == model.fk.front.dim + 2
    one = Split(*(getattr(moved, f) for f in ("servo", "x", "features", "cc_tip", "tip")),
                torch.cat([moved.memory[:, :1], split.memory[:, 1:]], 1))     # only segment 0's memory set
    with torch.no_grad():
        base, first = model.corrections(split), model.corrections(one)
        assert (base[:, 0] - first[:, 0]).abs().max() > 1e-3                   # segment 0 sees it
        assert torch.allclose(base[:, 1], first[:, 1], rtol=0, atol=1e3 * torch.finfo(torch.float64).eps)
        assert (model(moved) - model(split)).abs().max() > 1e-4


def test_history_variant_fits_a_direction_dependent_offset(compositional_split):
    """A tip offset proportional to the memory (hysteresis) is learnt by the history variant, not the static one."""
    cc, split = compositional_split
    moved = _with_memory(split)
    target = Split(moved.servo, moved.x, moved.features, moved.cc_tip,
                   moved.cc_tip + 4e-3 * moved.memory.sum(1) @ torch.tensor([[1.0, 0.0, 0.2], [0.0, 1.0, -0.3]],
                                                                            dtype=torch.float64), moved.memory)
    errors = {}
    for history in (False, True):
        torch.manual_seed(0)
        model = CCCompositionalResidual(cc, steps=60, lr=2e-2, weight_decay=0.0, history=history)
        model.fit(target)
        with torch.no_grad():
            errors[history] = float((model(target) - target.tip).pow(2).sum(-1).mean().sqrt())
    assert errors[True] < 0.5 * errors[False], errors


