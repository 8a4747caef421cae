"""The calibrated Cosserat-rod model of a tendon robot (dacr_learn.hardware.cosserat_model) and the registry
models built on it (dacr_learn.hardware.cosserat_learned)."""
from __future__ import annotations

import pytest
import torch
from hardware_testkit import LABELLED_IDS, LABELLED_ROBOT, labelled_servo_map

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.cosserat_learned import (
    CCClarkeResidualCosserat,
    CCClarkeResidualHistoryCosserat,
    CosseratOnly,
    _shared,
    calibration_key,
)
from dacr_learn.hardware.cosserat_model import CalibratedCosserat
from dacr_learn.hardware.deploy.checkpoint import _structure
from dacr_learn.hardware.learned import CCClarkeResidual, CCClarkeResidualHistory, synthetic_split
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


def calibrated_cc(strain: bool = True) -> CalibratedCC:
    """The labelled two-segment robot's CC model with non-trivial radius, frame, rotation and pretension
    parameters (unequal effective radii: tendons kink where they pass into the next segment)."""
    cc = CalibratedCC(RobotSpec.from_dict(LABELLED_ROBOT), compliance=2e-6, pretension_strain=strain)
    with torch.no_grad():
        cc.encoder.rotation.copy_(torch.tensor([0.03, -0.05]))
        cc.encoder.log_radius_scale.copy_(torch.tensor([0.08, -0.06]))
        cc.encoder.pretension.fill_(2e-4)
        if strain:
            cc.encoder.pretension_strain.fill_(3e-4)
        cc.base_tilt.copy_(torch.tensor([0.02, -0.01]))
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005]))
        cc.tip_offset.fill_(6e-3)
        cc.marker_lateral.copy_(torch.tensor([2e-3, -1e-3]))
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc


def commands(cc: CalibratedCC, n: int, seed: int) -> torch.Tensor:
    """Displacements (n, 6) [m] bending both segments at once (the pre-training sampler)."""
    spec = cc.spec
    return synthetic_split(cc, labelled_servo_map(spec), LABELLED_IDS, n, seed).x


@pytest.mark.parametrize("strain", [False, True])
def test_weightless_and_axially_rigid_it_is_the_cc_model(strain):
    """With no weight and an inextensible backbone, the rod's equilibrium is the slack-aware CC encoder's energy
    minimum: the same tip to micrometres, over mixed taut/slack commands (an independent check of both)."""
    cc = calibrated_cc(strain)
    x = commands(cc, 48, seed=0)
    x[::3, 1] -= 4e-3                                   # some tendons released far: slack
    cosserat = CalibratedCosserat(cc, axial_radius=1e-5)
    err = (cosserat(x) - cc(x)).norm(dim=-1)
    assert float(err.max()) < 5e-6
    # the model is not the CC one: a weight or a compressible backbone moves the tip by a lot more
    heavy = CalibratedCosserat(cc, weight=0.5, axial_radius=1e-5)
    soft = CalibratedCosserat(cc, axial_radius=1e-3)
    assert float((heavy(x) - cc(x)).norm(dim=-1).max()) > 1e-4
    assert float((soft(x) - cc(x)).norm(dim=-1).max()) > 1e-4


QUICK_FIT = {"rows": 32, "iterations": 2, "starts": (5e-5,)}


def test_the_weight_is_a_free_direction_with_a_non_negative_magnitude():
    """g = w·u in the motion-capture frame, rotated into the tilted base (to rounding); w ≥ 0 by construction, a
    weight past WEIGHT_MAX held to it."""
    cc = calibrated_cc()
    side = CalibratedCosserat(cc, weight=0.3, direction=(0.0, -2.0, 0.0), axial_radius=1e-5)
    assert side.weight == pytest.approx(0.3) and torch.allclose(side.direction(), torch.tensor([0.0, -1.0, 0.0],
                                                                                                dtype=torch.float64))
    expected = cc.base_rotation().detach().double().T @ torch.tensor([0.0, -0.3, 0.0], dtype=torch.float64)
    assert torch.allclose(side.gravity(), expected, rtol=0, atol=1e-15)
    report = side.report()
    assert report["gravity_direction_mocap"] == [0.0, -1.0, 0.0] and report["gravity_from_mocap_down_deg"] == 90.0
    assert report["gravity_azimuth_deg"] == -90.0 and 80.0 < report["gravity_to_base_axis_deg"] < 100.0
    side.set_physics({"gravity": torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)})  # held to WEIGHT_MAX
    assert side.weight == pytest.approx(0.5) and float(side.direction()[2]) == pytest.approx(1.0)
    for bad in ({"weight": -0.1}, {"direction": (0.0, 0.0, 0.0)}):
        with pytest.raises(ValueError, match="weight >= 0"):
            CalibratedCosserat(cc, **bad)


def test_a_weight_across_the_robot_bends_it_sideways_unlike_one_along_its_axis():
    """The solves of the free direction (:func:`test_the_weight_is_a_free_direction_with_a_non_negative_magnitude`):
    a weight along mocap −y moves the tips towards −y and at least three times as far as one along −z (≈ the axis)."""
    cc = calibrated_cc()
    side = CalibratedCosserat(cc, weight=0.3, direction=(0.0, -2.0, 0.0), axial_radius=1e-5)
    x = commands(cc, 8, seed=3)
    axial = CalibratedCosserat(cc, weight=0.3, axial_radius=1e-5)                      # along mocap −z (≈ the axis)
    moved, along = side(x) - cc(x), axial(x) - cc(x)                                    # tips [m]
    assert float(moved[:, 1].mean()) < -1e-4
    assert float(moved.norm(dim=-1).mean()) > 3 * float(along.norm(dim=-1).mean())


def test_calibrations_are_shared_through_files_between_processes(tmp_path):
    """_shared computes a key once; a process that has not computed it (its in-process cache empty) reads the
    file instead of computing it again."""
    from dacr_learn.hardware import cosserat_learned

    calls = []

    def compute():
        calls.append(1)
        return {"value": torch.arange(3)}

    first = _shared("k1", compute, tmp_path)
    cosserat_learned._SHARED.pop("k1")                                # as another process would start
    second = _shared("k1", compute, tmp_path)
    assert len(calls) == 1 and torch.equal(first["value"], second["value"])
    assert (tmp_path / "k1.pkl").exists()
    cc = calibrated_cc()
    split = synthetic_split(cc, labelled_servo_map(cc.spec), LABELLED_IDS, 8, 0)
    assert calibration_key(cc, split, {}) != calibration_key(cc, split, {"free_frame": False})
    assert calibration_key(cc, split, {}) != calibration_key(cc, split.rows(torch.arange(7)), {})


@pytest.mark.slow
def test_fit_recovers_the_weight_and_the_tips_of_a_known_robot():
    cc = calibrated_cc()
    truth = CalibratedCosserat(cc, weight=0.4, axial_radius=3e-4, direction=(0.3, -1.0, -0.2))  # not along an axis
    x = commands(cc, 48, seed=1)
    tip = truth(x)
    model = CalibratedCosserat(cc)                                # starts from w = 0 and a stiffer backbone
    info = model.fit(x, tip, rows=48, iterations=3, starts=(5e-5,))    # 3: rms 3.6e-6 m, w 0.399 (6: 5.6e-7, 0.3998)
    assert info["rms_m"] < 0.1 * info["rms_before_m"] and info["rms_m"] < 2e-5
    assert abs(model.weight - 0.4) < 0.05
    assert float(model.direction() @ truth.direction()) > 0.99    # within 8° of the true direction
    fresh = commands(cc, 32, seed=2)
    assert float((model(fresh) - truth(fresh)).norm(dim=-1).max()) < 1e-4
    assert model.report()["weight_per_length_N_per_m"] == pytest.approx(model.weight, abs=1e-5)


@pytest.mark.slow
def test_registry_models_fit_predict_and_the_residual_one_ships_as_a_clarke_residual(compositional_split, monkeypatch):
    """The networks train 30 full-batch steps instead of 1 500 + 500 (that was 70 s of this test): what is checked
    here is the plumbing (calibration cache, synthetic pre-training split, the deployable class, fallbacks)."""
    import dacr_learn.hardware.learned as learned  # its pretrain_and_finetune trains the residual networks

    brief = learned.train_full_batch
    monkeypatch.setattr(learned, "train_full_batch", lambda params, loss, steps=0, lr=learned.LR:
                        brief(params, loss, steps=30, lr=lr))
    cc, split = compositional_split
    physics = CosseratOnly(cc, QUICK_FIT)
    with pytest.raises(ValueError, match="fit"):
        physics(split)
    physics.fit(split)
    tips = physics(split)                              # each call solves the rod for every row: computed once
    assert tips.shape == (len(split.tip), 3)
    assert float((tips - split.tip).norm(dim=-1).mean()) < 1e-4   # the data are the CC model's own
    again = CosseratOnly(cc, QUICK_FIT)
    again.fit(split)                                   # the same rows and CC model: the cached calibration, a copy
    assert again.model is not physics.model and torch.equal(again(split), tips)
    solved = physics.model

    def failing_first_row(x):                   # a command whose solve fails gets the CC model's tip, counted
        tip = solved(x)
        tip[0] = torch.nan
        return tip

    physics.model = failing_first_row
    fallback = physics(split)
    assert physics.fallbacks == 1 and torch.equal(fallback[0], split.cc_tip[0])
    physics.model = solved
    other = CosseratOnly(cc, {**QUICK_FIT, "rows": 16, "iterations": 1})     # the option reaches the fit
    other.fit(split)
    assert other.fit_report["rows"] == 16 and other.fit_report["iterations"] <= 1
    torch.manual_seed(0)
    residual = CCClarkeResidualCosserat(cc, labelled_servo_map(cc.spec), LABELLED_IDS, synthetic_seed=3, samples=96,
                                        fit_options=QUICK_FIT)
    residual.fit(split)
    pred = residual(split)
    assert pred.shape == (len(split.tip), 3) and bool(torch.isfinite(pred).all())
    assert _structure([residual]) == "clarke_residual"
    plain = CCClarkeResidual(cc)
    plain.load_state_dict(residual.state_dict())                  # loads into the deployable class unchanged
    assert torch.equal(plain(split), pred)
    torch.manual_seed(0)
    history = CCClarkeResidualHistoryCosserat(cc, labelled_servo_map(cc.spec), LABELLED_IDS, synthetic_seed=3,
                                              samples=96, fit_options=QUICK_FIT)
    history.fit(split)                                            # the same calibration and synthetic tips (cached)
    assert history.fit_report == residual.fit_report and history.history
    assert _structure([history]) == "clarke_residual"
    deployed = CCClarkeResidualHistory(cc)
    deployed.load_state_dict(history.state_dict())                # ships as a cc_clarke_residual_history model
    assert torch.equal(deployed(split), history(split))


def test_the_history_model_on_the_cosserat_physics_saves_and_loads_as_a_history_model(compositional_split, tmp_path):
    """cc_clarke_residual_history_cosserat is deployable: its members save with their play-memory input and load
    into CCClarkeResidualHistory (the exported history modules' model) with the same predictions."""
    from dacr_learn.hardware.deploy.checkpoint import HardwareModel, load_hardware_model, save_hardware_model

    cc, split = compositional_split
    torch.manual_seed(0)
    member = CCClarkeResidualHistoryCosserat(cc, labelled_servo_map(cc.spec), LABELLED_IDS, synthetic_seed=3)
    member.fit_normalization(split)
    with torch.no_grad():
        member.net[-1].weight.normal_(0.0, 0.5)           # a correction that matters, and depends on the memory
    model = HardwareModel("cc_clarke_residual_history_cosserat", cc.spec, labelled_servo_map(cc.spec), LABELLED_IDS,
                          cc, [member.eval()])
    loaded = load_hardware_model(save_hardware_model(model, tmp_path / "model.pt"))
    assert loaded.history and isinstance(loaded.members[0], CCClarkeResidualHistory)
    servo = 1e3 * split.servo
    assert torch.allclose(loaded.predict(servo)[0], model.predict(servo)[0], rtol=0, atol=1e-12)
    moved = split.rows(torch.arange(len(split)))                   # (this split's memory is 0: synthetic commands)
    moved.memory = torch.full_like(moved.memory, 0.7)
    with torch.no_grad():
        assert float((member(moved) - member(split)).abs().max()) > 1e-6   # the memory input is used
