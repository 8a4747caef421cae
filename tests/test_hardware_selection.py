"""Model registry, train-only selection proxies, the default model and the carry-over options.

The ``labelled_robot_dir`` fixture (tests/conftest.py, built by hardware_testkit.write_labelled_robot):
a small synthetic two-segment robot (the calibrated CC model is its ground truth, 0.1 mm noise) with
labelled single-segment and pair patterns stands in for a hardware recording; its folder has no
val.csv, like data/ftdcr_v6.
"""
from __future__ import annotations

import json

import pytest
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.learned import make_split
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.pool import TaskPool
from dacr_learn.hardware.study.registry import MODELS, REGISTRY, FitContext, build_model, model_info
from dacr_learn.hardware.study.selection import (
    choose_default,
    make_folds,
    pattern_family,
    proxy_masks,
    proxy_scores,
)
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
def test_registry_has_unique_letters_and_flags():
    letters = [REGISTRY[m].letter for m in MODELS]
    assert len(set(letters)) == len(letters) == len(MODELS)
    assert {m for m in MODELS if REGISTRY[m].deterministic} == {"linear_raw", "cc"}
    assert [m for m in MODELS if not REGISTRY[m].static] == ["cc_clarke_residual_history", "cc_compositional_history"]
    history = model_info("cc_compositional_history")
    assert history.letter == "k" and history.clarke_space and not history.deployable
    assert not model_info("mlp_raw").clarke_space and model_info("pretrained_clarke").clarke_space
    with pytest.raises(ValueError, match="expected one of"):
        model_info("mlp")
    with pytest.raises(ValueError, match="expected one of"):      # no ad-hoc variants: only what can ship is scored
        model_info(REGISTRY["cc"])


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


def test_cli_without_val_records_the_default_model(labelled_robot_dir, tmp_path):
    from dacr_learn.hardware.study.cli import main

    data, robot = labelled_robot_dir
    out = tmp_path / "run"
    report = main(["--data", str(data), "--robot", str(robot), "--out", str(out),
                   "--models", "linear_raw", "cc", "--seeds", "0"])
    results = json.loads((out / "results.json").read_text())
    assert results["default_model"] == report["default_model"] == "cc"
    assert results["selection"]["candidates"] == ["cc"] and results["val"] is None
    assert set(results["selection"]["scores"]) == {"linear_raw", "cc"}
    assert results["selection"]["proxies"] == ["extrap"]                   # the family CV only on request
    assert "cv" not in results["selection"]["scores"]["cc"] and "| – |" in (out / "results.md").read_text()
    assert "val" not in results["models"]["cc"] and results["models"]["cc"]["train"]["rmse_mm"]["mean"] < 0.3
    assert not (out / "val_predictions.csv").exists()
    assert "**`cc`** (default)" in (out / "results.md").read_text()


def test_cli_computes_the_family_cv_on_request_and_keeps_the_default(labelled_robot_dir, tmp_path):
    from dacr_learn.hardware.study.cli import main, parse_args

    data, robot = labelled_robot_dir
    args = ["--data", str(data), "--robot", str(robot), "--models", "linear_raw", "cc", "--seeds", "0"]
    full = main(args + ["--out", str(tmp_path / "full"), "--proxies", "cv", "extrap"])
    short = main(args + ["--out", str(tmp_path / "short")])
    assert full["default_model"] == short["default_model"] == "cc" and full["selection"]["proxies"] == ["cv", "extrap"]
    for name in ("linear_raw", "cc"):
        f, s = full["selection"]["scores"][name], short["selection"]["scores"][name]
        assert set(f["cv_folds"]) == {"single", "pair12"} and f["extrap"] == pytest.approx(s["extrap"], rel=1e-9)
    with pytest.raises(SystemExit):
        parse_args(args + ["--out", str(tmp_path), "--proxies", "cv"])    # the default is chosen on extrap


def test_a_model_built_in_a_worker_process_equals_the_one_built_here(labelled_robot_dir):
    ctx = _context(labelled_robot_dir)
    with TaskPool(jobs=2) as pool:
        remote = pool.submit(build_model, "mlp_clarke", ctx, 0)
        here = pool.run_here(build_model, "mlp_clarke", ctx, 0)
        (got, seconds), (want, _) = remote.result(), here.result()
    assert seconds > 0
    for (key, a), b in zip(got.state_dict().items(), want.state_dict().values(), strict=True):
        assert torch.allclose(a, b, rtol=0, atol=1e-7), key                # seeded in the worker: the same start
    other = build_model("mlp_clarke", ctx, 1).net[0].weight
    assert not torch.allclose(got.net[0].weight, other)                    # …and the seed matters
    with pytest.raises(ValueError, match="jobs >= 1"):
        TaskPool(jobs=0)


def _context(labelled_robot_dir) -> FitContext:
    data, robot = labelled_robot_dir
    spec = RobotSpec.from_yaml(robot)
    smap = ServoMap.from_yaml(robot.parent / "servo_maps" / robot.name)
    rec = load_recording(data / "train.csv", spec)
    cc = CalibratedCC(spec)
    for p in cc.parameters():
        p.requires_grad_(False)
    return FitContext(cc, smap, rec.servo_ids, make_split(rec, spec, smap, cc))


def test_the_default_is_chosen_among_models_that_save_and_the_others_are_reported(labelled_robot_dir, tmp_path):
    """`deployable` in the registry is what checkpoint.save_hardware_model accepts: every deployable model
    saves; a Clarke-space model that is not deployable is reported as the proxy's best but never the default."""
    from dacr_learn.hardware.deploy.checkpoint import HardwareModel, save_hardware_model
    from dacr_learn.hardware.learned import cc_as_residual
    from dacr_learn.hardware.study.benchmark import default_candidates, load_setup

    data, robot = labelled_robot_dir
    setup = load_setup(robot, data / "train.csv", None, tmp_path)
    for name in MODELS:
        info = model_info(name)
        member = cc_as_residual(setup.train, setup.cc) if name == "cc" else build_model(name, setup.context(), 0)
        model = HardwareModel(name, setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc, [member])
        if info.deployable:
            assert save_hardware_model(model, tmp_path / f"{name}.pt").exists()
        else:
            with pytest.raises(ValueError, match="members"):
                save_hardware_model(model, tmp_path / f"{name}.pt")
    assert set(default_candidates(MODELS)) == {m for m in MODELS if model_info(m).clarke_space
                                               and model_info(m).deployable}
    assert "cc_compositional_residual" in default_candidates(MODELS, deployable_only=False)
    blocked = next(m for m in default_candidates(MODELS, deployable_only=False) if not model_info(m).deployable)
    scores = {m: {"extrap": 1.0 if m == blocked else 2.0 + i} for i, m in enumerate(MODELS)}
    assert choose_default(scores, default_candidates(list(scores)), "extrap") == "cc"


def test_save_bundles_the_final_runs_models_instead_of_training_them_again(labelled_robot_dir, tmp_path,
                                                                            monkeypatch):
    """``--save`` (two worker processes): the saved ensemble is the benchmark's own final-run models, returned
    from the workers, and the σ model's held-out fits run in the workers too — nothing is trained in this
    process (fit_model / the held-out build_model here raise). The members predict like the same model
    trained here per seed, the reported train RMSE per seed is the saved member's, and the σ model equals
    sigma_models computed here."""
    from dacr_learn.hardware.deploy.checkpoint import load_hardware_model
    from dacr_learn.hardware.metrics import tip_metrics
    from dacr_learn.hardware.study import benchmark, heldout
    from dacr_learn.hardware.study.cli import main

    data, robot = labelled_robot_dir
    out, save = tmp_path / "run", tmp_path / "model"
    fit_model = benchmark.fit_model

    def no_fit_here(*args):
        raise AssertionError(f"{args[0]} trained in the main process by --save (the default again, or its σ folds)")

    with monkeypatch.context() as patch:
        patch.setattr(benchmark, "fit_model", no_fit_here)      # the spawned workers import their own, unpatched
        patch.setattr(heldout, "build_model", no_fit_here)
        report = main(["--data", str(data), "--robot", str(robot), "--out", str(out), "--models",
                       "cc_clarke_residual", "--seeds", "0", "1", "--jobs", "2", "--save", str(save)])
    assert report["default_model"] == "cc_clarke_residual"
    saved = load_hardware_model(save / "model.pt")
    setup = benchmark.load_setup(robot, data / "train.csv", None, tmp_path / "setup",
                       cc_variant=report["cc_fit"]["variant"]["chosen"])
    per_seed = report["models"]["cc_clarke_residual"]["train"]["rmse_mm"]["per_seed"]
    assert len(saved.members) == 2
    for seed, member in zip((0, 1), saved.members, strict=True):
        reference = fit_model("cc_clarke_residual", setup, seed).eval()
        with torch.no_grad():
            want, got = reference(setup.train), member(setup.train)
            assert torch.allclose(got, want, rtol=0, atol=1e-9)               # [m]: the same fit
            assert tip_metrics(got, setup.train.tip)["rmse_mm"] == pytest.approx(per_seed[seed], abs=1e-3)
    calibration, sigma_model = heldout.sigma_models(setup, "cc_clarke_residual", [0, 1])
    assert saved.sigma_model.terms == sigma_model.terms
    assert torch.allclose(saved.sigma_model.coefficients, sigma_model.coefficients, rtol=1e-6, atol=1e-12)
    assert float(saved.sigma_model.floor) == pytest.approx(float(sigma_model.floor), rel=1e-6)
    assert float(saved.sigma.scale) == pytest.approx(float(calibration.scale), rel=1e-6)
