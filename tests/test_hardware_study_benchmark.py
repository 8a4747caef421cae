"""The benchmark's setup, model fits and default candidates (dacr_learn.hardware.study.benchmark)."""
from __future__ import annotations

import pytest
import torch
from conftest import ROOT, roundoff_tol
from hardware_testkit import V4_TIP_SCALE, v4_commands

from dacr_learn.hardware.compositional_model import CCCompositionalResidual
from dacr_learn.hardware.deploy.checkpoint import load_hardware_model, save_hardware_model
from dacr_learn.hardware.study.benchmark import fit_hardware_model
from dacr_learn.hardware.study.registry import MODELS, REGISTRY, ModelInfo, build_model, model_info
from dacr_learn.hardware.study.selection import default_choice

pytestmark = pytest.mark.usefixtures("one_thread")


def test_load_setup_records_the_cc_variant_and_refuses_an_unknown_one(tmp_path):
    from dacr_learn.hardware.study.benchmark import load_setup

    robot, data = ROOT / "configs/robots/ftdcr_v4_calibrated.yaml", ROOT / "data/ftdcr_v4"
    setup = load_setup(robot, data / "train.csv", None, tmp_path, cc_variant="strain")
    assert setup.cc.encoder.strain and setup.cc_options == {"pretension_strain": True}
    assert setup.cc_fit["variant"] == {"requested": "strain", "chosen": "strain"}
    with pytest.raises(ValueError, match="cc_variant: expected 'auto' or one of"):
        load_setup(robot, data / "train.csv", None, tmp_path, cc_variant="stiff")


def test_fit_hardware_model_trains_a_compositional_ensemble(v4_slice, monkeypatch, tmp_path):
    quick = ModelInfo("cc_compositional_residual", lambda c, s: CCCompositionalResidual(c.cc, steps=5),
                      "clarke", deployable=True)
    monkeypatch.setitem(REGISTRY, "cc_compositional_residual", quick)
    model = fit_hardware_model(v4_slice, "cc_compositional_residual", [0, 1])
    assert len(model.members) == 2 and model.compositional and not model.history
    assert not any(m.training for m in model.members)
    loaded = load_hardware_model(save_hardware_model(model, tmp_path / "fitted.pt"))
    servo = v4_commands(v4_slice)
    assert (loaded.predict(servo)[0] - model.predict(servo)[0]).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE)


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
    assert default_choice(scores, default_candidates(list(scores)), "extrap")["default"] == "cc"


def test_shared_cosserat_pieces_are_submitted_once_calibrations_first(compositional_split, tmp_path):
    """The benchmark hands each Cosserat calibration and each seed's synthetic tips to its pool once (the residual
    and its history variant share them), every calibration ahead of every synthetic set, each a call that binds to
    its function; in line (one job) it hands none (the fits compute them when asked)."""
    import inspect

    from hardware_testkit import LABELLED_IDS, labelled_servo_map

    from dacr_learn.hardware.study.benchmark import submit_warmups
    from dacr_learn.hardware.study.registry import FitContext

    cc, split = compositional_split
    ctx = FitContext(cc, labelled_servo_map(cc.spec), LABELLED_IDS, split, tmp_path)

    class Recorder:
        jobs = 2
        calls: list = []

        def submit(self, fn, *args):
            inspect.signature(fn).bind(*args)               # a call the worker can make
            self.calls.append((fn.__name__, args))

    pool = Recorder()
    submit_warmups(pool, [(ctx, "cosserat", [0]), (ctx, "cc_clarke_residual_cosserat", [0, 1]),
                          (ctx, "cc_clarke_residual_history_cosserat", [0, 1]), (ctx, "cc_clarke_residual", [0])])
    names = [name for name, _ in pool.calls]
    assert names == ["_calibrate", "_calibrate", "_synthesize", "_synthesize"]
    assert [args[2] for name, args in pool.calls if name == "_calibrate"] == [tmp_path, tmp_path]
    assert sorted(args[5] for name, args in pool.calls if name == "_synthesize") == [1000, 1001]   # synthetic seeds
    pool.jobs = 1
    assert submit_warmups(pool, [(ctx, "cosserat", [0])]) == []
