"""Train-only model selection (dacr_learn.hardware.study.selection): pattern families, the proxy masks and scores,
the default model, and the CC variant chosen by the singles-to-pairs score.

The ``labelled_robot_dir`` fixture (tests/conftest.py, built by hardware_testkit.write_labelled_robot):
a small synthetic two-segment robot (the calibrated CC model is its ground truth, 0.1 mm noise) with
labelled single-segment and pair patterns stands in for a hardware recording; its folder has no
val.csv, like data/ftdcr_v6.
"""
from __future__ import annotations

import pytest
import torch
from conftest import ROOT

from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.selection import (
    default_choice,
    make_folds,
    pattern_family,
    proxy_masks,
    proxy_scores,
)
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


def test_pattern_families_and_proxy_masks():
    labels = ["rep1_tendon3_id9_pull", "rep1_seg2_circle", "rep2_pair13_opp_dir90_hold", "rep1_pair12_same_dir0",
              "rep1_seg1_dir0_hold"]
    assert [pattern_family(label) for label in labels] == ["single", "single", "pair13", "pair12", "single"]
    masks = proxy_masks(labels)
    assert [name for name, _, _ in masks["cv"]] == ["single", "pair12", "pair13"]
    for _, tr, te in masks["cv"]:                       # each fold holds out exactly one family
        assert not (tr & te).any() and (tr | te).all()
    (_, tr, te), = masks["extrap"]
    assert tr.tolist() == [True, True, False, False, True] and te.tolist() == [not t for t in tr.tolist()]
    with pytest.raises(ValueError, match="'pair<jk>'"):
        pattern_family("random")
    with pytest.raises(ValueError, match="expected 'single' and at least one pair family"):
        proxy_masks(["rep1_pair12_same", "rep1_pair13_opp"])
    assert list(proxy_masks(labels, ["extrap"])) == ["extrap"]            # only the requested proxies
    assert [m[0] for m in proxy_masks(labels, ["extrap", "cv"])["cv"]] == ["single", "pair12", "pair13"]
    with pytest.raises(ValueError, match="expected one or more of"):
        proxy_masks(labels, ["loo"])


def test_default_choice_takes_the_lowest_proxy():
    scores = {"cc": {"extrap": 6.3, "cv": 5.9}, "mlp_clarke": {"extrap": 9.0, "cv": 5.0}, "mlp_raw": {"extrap": 1.0}}
    assert default_choice(scores, ["cc", "mlp_clarke"])["default"] == "cc"
    assert default_choice(scores, ["cc", "mlp_clarke"], "cv")["default"] == "mlp_clarke"
    with pytest.raises(ValueError, match="has a 'extrap' score"):
        default_choice(scores, ["pretrained_clarke"])


def test_proxies_score_the_true_model_at_the_noise(labelled_robot_dir):
    data, robot = labelled_robot_dir
    spec = RobotSpec.from_yaml(robot)
    smap = ServoMap.from_yaml(robot.parent / "servo_maps" / robot.name)
    rec = load_recording(data / "train.csv", spec)
    masks = proxy_masks(rec.labels)
    folds = {p: make_folds(rec, spec, smap, m) for p, m in masks.items()}
    assert [len(f.test) for f in folds["cv"]] == [80, 40] and len(folds["extrap"][0].test) == 40
    cc, lin = proxy_scores("cc", folds, [0, 1]), proxy_scores("linear_raw", folds, [0])
    assert cc["seeds"] == [0]                            # deterministic: one run
    assert cc["extrap"] < 0.3 and cc["cv"] < 0.3         # the CC model is the truth (0.17 mm noise RMS)
    assert lin["extrap"] > 3 * cc["extrap"] and set(lin["cv_folds"]) == {"single", "pair12"}


def test_cc_variant_is_chosen_by_the_singles_to_pairs_score_of_the_cc_model(v4_train_head):
    from dacr_learn.hardware.study.selection import CC_VARIANTS, choose_cc_variant, fold_rmse, make_folds, proxy_masks

    spec, smap, _ = v4_train_head
    rec = load_recording(ROOT / "data/ftdcr_v4/train.csv", spec)
    chosen, scores = choose_cc_variant(rec, spec, smap)
    assert set(scores) == set(CC_VARIANTS) and chosen == min(scores, key=scores.get)
    masks = proxy_masks(rec.labels, ("extrap",))["extrap"]
    fold, = make_folds(rec, spec, smap, masks, CC_VARIANTS["strain"])
    assert fold.ctx.cc.encoder.strain                          # the folds are built with the variant's CC model
    assert abs(fold_rmse("cc", fold, 0) - scores["strain"]) <= 1e-3   # same fit, same score [mm] (rounded to 1e-4)
    with pytest.raises(ValueError, match="cc variants: expected one or more of"):
        choose_cc_variant(rec, spec, smap, ("stiff",))


# --------------------------------------------------------------------------------------------------
# The proxies' noise: bootstrap over held-out pattern groups and seeds, and the one-standard-error rule
# --------------------------------------------------------------------------------------------------


def test_pattern_groups_join_a_pattern_and_its_hold_phase():
    from dacr_learn.hardware.study.selection import pattern_group

    assert pattern_group("rep1_pair13_same_dir60_hold") == pattern_group("rep1_pair13_same_dir60") == \
        pattern_group("rep2_pair13_same_dir60") == "pair13_same_dir60"
    assert pattern_group("rep1_pair13_opp_dir60") != pattern_group("rep1_pair13_same_dir60")


def test_bootstrap_weights_and_rmse_equal_the_resampled_rows():
    """Each replicate's weighted offset-removed RMSE equals offset_removed_rmse of the rows it stands for, written
    out (an independent computation: the drawn groups' rows concatenated)."""
    from dacr_learn.hardware.metrics import offset_removed_rmse
    from dacr_learn.hardware.study.selection import bootstrap_replicates, group_weights, weighted_rmse

    g = torch.Generator().manual_seed(4)
    groups = ["a"] * 3 + ["b"] * 5 + ["c"] * 2 + ["d"] * 4
    error = torch.randn(len(groups), 3, generator=g, dtype=torch.float64) + torch.tensor([2.0, -1.0, 0.5],
                                                                                         dtype=torch.float64)
    weights = group_weights(groups, 50, torch.Generator().manual_seed(0))
    assert weights.shape == (50, len(groups))
    names = sorted(set(groups))
    for row in weights:
        per_group = {gr: float(row[groups.index(gr)]) for gr in names}
        assert sum(per_group.values()) == len(names)                          # as many groups drawn as there are
        for i, gr in enumerate(groups):                                       # a row weighs as its group
            assert float(row[i]) == per_group[gr]
    rmse = weighted_rmse(error, weights)
    for b in range(10):
        rows = torch.cat([error[torch.tensor([i for i, gr in enumerate(groups) if gr == name])]
                          for name in names for _ in range(int(weights[b, groups.index(name)]))])
        assert float(rmse[b]) == pytest.approx(float(offset_removed_rmse(rows, torch.zeros_like(rows))), rel=1e-12)
    unit = weighted_rmse(error, torch.ones(1, len(groups), dtype=torch.float64))
    assert float(unit[0]) == pytest.approx(float(offset_removed_rmse(error, torch.zeros_like(error))), rel=1e-12)
    # one seed: the replicates are the weighted RMSE; two identical seeds: the same (seed resampling adds nothing)
    one = bootstrap_replicates({"f": [error]}, {"f": weights}, "m")
    two = bootstrap_replicates({"f": [error, error]}, {"f": weights}, "m")
    assert torch.allclose(one, rmse) and torch.allclose(two, rmse)
    # seeds that differ add their spread
    noisy = bootstrap_replicates({"f": [error, 3 * error]}, {"f": weights}, "m")
    assert float(noisy.std()) > float(one.std())
    with pytest.raises(ValueError, match="at least one row"):
        group_weights([], 5)


def test_default_is_the_simplest_candidate_within_the_combined_uncertainty():
    from dacr_learn.hardware.study.selection import default_choice

    scores = {"cc": {"extrap": 5.30}, "cc_clarke_residual": {"extrap": 5.10},
              "cc_clarke_residual_history": {"extrap": 4.90}, "cc_compositional_residual": {"extrap": 4.95}}
    candidates = list(scores)
    g = torch.Generator().manual_seed(1)
    common = torch.randn(4000, generator=g, dtype=torch.float64)           # the shared test patterns move all

    def reps(spread: float) -> dict:
        return {m: scores[m]["extrap"] + common + spread * torch.randn(4000, generator=g, dtype=torch.float64)
                for m in candidates}

    tight = default_choice(scores, candidates, "extrap", reps(0.01))       # every gap far beyond its noise
    assert tight["default"] == tight["best"] == "cc_clarke_residual_history" and tight["tied"] == [tight["best"]]
    # the paired difference cancels what the models share: a huge common spread alone ties nothing
    assert all(r["gap_std_mm"] < 0.05 for r in tight["candidates"].values())
    assert tight["candidates"]["cc"]["std_mm"] > 0.9
    loose = default_choice(scores, candidates, "extrap", reps(0.2))        # σ of a difference ≈ 0.28 mm
    assert loose["best"] == "cc_clarke_residual_history"
    assert set(loose["tied"]) == {"cc_clarke_residual_history", "cc_compositional_residual", "cc_clarke_residual"}
    assert loose["default"] == "cc_clarke_residual"                         # the simplest of the tied
    assert "cc_clarke_residual" in loose["reason"] and loose["rule"].startswith("one-standard-error")
    wide = default_choice(scores, candidates, "extrap", reps(1.0))
    assert wide["default"] == "cc" and len(wide["tied"]) == 4
    # without replicates: the lowest score (the rule before its noise was known)
    assert default_choice(scores, candidates, "extrap")["default"] == "cc_clarke_residual_history"
    with pytest.raises(ValueError, match="missing"):
        default_choice(scores, candidates, "extrap", {"cc": common})


def test_complexity_orders_static_before_history_and_fewer_outputs_first():
    from dacr_learn.hardware.study.registry import complexity

    order = sorted(["cc_clarke_residual_history_cosserat", "cc_clarke_residual_history", "cc_compositional_residual",
                    "cc_clarke_residual_cosserat", "cc_clarke_residual", "cc"], key=complexity)
    assert order == ["cc", "cc_clarke_residual", "cc_clarke_residual_cosserat", "cc_compositional_residual",
                     "cc_clarke_residual_history", "cc_clarke_residual_history_cosserat"]
