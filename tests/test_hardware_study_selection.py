"""Train-only model selection (dacr_learn.hardware.study.selection): pattern families, the proxy masks and scores,
the default model, and the CC variant chosen by the singles-to-pairs score.

The ``labelled_robot_dir`` fixture (tests/conftest.py, built by hardware_testkit.write_labelled_robot):
a small synthetic two-segment robot (the calibrated CC model is its ground truth, 0.1 mm noise) with
labelled single-segment and pair patterns stands in for a hardware recording; its folder has no
val.csv, like data/ftdcr_v6.
"""
from __future__ import annotations

import pytest
from conftest import ROOT

from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.selection import (
    choose_default,
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


def test_choose_default_takes_the_lowest_proxy():
    scores = {"cc": {"extrap": 6.3, "cv": 5.9}, "mlp_clarke": {"extrap": 9.0, "cv": 5.0}, "mlp_raw": {"extrap": 1.0}}
    assert choose_default(scores, ["cc", "mlp_clarke"]) == "cc"
    assert choose_default(scores, ["cc", "mlp_clarke"], "cv") == "mlp_clarke"
    with pytest.raises(ValueError, match="has a 'extrap' score"):
        choose_default(scores, ["pretrained_clarke"])


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
