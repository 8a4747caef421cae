"""The body of every model (dacr_learn.body): the compositional model's segment twists, the FK networks' shape
output and its training on the data's backbones, the Cosserat rod's nodes, the hardware models' calibrated body and
the solver adapters, against exact references (the CC arcs of kinematics.backbone_points, a straight rod, the
weightless rod = the CC model)."""
from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from conftest import ROOT

from dacr_learn.body import BodyPoints, body_layout, cc_body, segment_body_radii, subsample
from dacr_learn.compositional import CompositionalFK
from dacr_learn.cosserat import solve_statics
from dacr_learn.data import cosserat as cosserat_data
from dacr_learn.data import generate
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.ik.adapters import as_solver_model
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.models import FKModel
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
ROBOTS = ROOT / "configs" / "robots"


def exact_compositional(spec: RobotSpec, q: torch.Tensor) -> CompositionalFK:
    """A compositional model whose per-segment map is the exact CC twist: the network's last layer is zero, the
    skip and the bias give ξ = (0, 0, β/l; −ρ_im/d, ρ_re/d, 0) of the strain-unit features (docs/compositional.md)."""
    model = CompositionalFK(spec, width=8, depth=1).to(F64)
    model.fit_normalization(q)
    std, mean = model.front.norm.std, model.front.norm.mean
    cc_map = torch.zeros(6, 4, dtype=F64)
    cc_map[2, 2], cc_map[3, 1], cc_map[4, 0] = 1.0, -1.0, 1.0
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.copy_(cc_map @ mean)
        model.skip.weight.copy_(cc_map * std)
    return model


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "type3", "hetero_4seg_types"])
def test_a_compositional_model_with_exact_segment_features_has_the_cc_body(robot):
    """Exact per-segment twists → the CC arcs at every point to rounding (bending, extending and rolled segments),
    and the body ends at the model's own tip."""
    spec = RobotSpec.from_yaml(ROBOTS / f"{robot}.yaml")
    data = generate(spec, 64, seed=3, dtype=F64)
    model = exact_compositional(spec, data["q"])
    body, reference = model.body(data["q"], 7), cc_body(spec, data["features"], 7)
    tol = 1e3 * torch.finfo(F64).eps * spec.total_length         # the standardisation round trip and exp rounding
    assert body.points.shape == (64, 1 + 7 * spec.num_segments, 3)
    assert torch.allclose(body.points, reference.points, rtol=0, atol=tol)
    assert torch.allclose(body.points[:, -1], model(data["q"])[:, :3, 3], rtol=0, atol=tol)
    assert torch.equal(body.arc_length, reference.arc_length) and torch.equal(body.radius, reference.radius)


def test_the_body_layout():
    """P = 1 + m·K points at the fractions j/K of each segment's reference length; radii: the largest joint radius
    of the segment (no body_radius in the file); a dense NumPy-free check of the arcs."""
    spec = RobotSpec.from_yaml(ROBOTS / "hetero_3seg_coupled.yaml")
    arcs, radii = body_layout(spec, 4)
    expected, start = [0.0], 0.0
    for seg in spec.segments:
        expected += [start + seg.length * j / 4 for j in range(1, 5)]
        start += seg.length
    assert arcs.tolist() == pytest.approx(expected, abs=1e-15) and arcs[-1] == pytest.approx(spec.total_length)
    assert bool((arcs.diff() > 0).all())
    assert radii.tolist() == [max(spec.segments[0].joint_radii)] + [
        r for r in segment_body_radii(spec) for _ in range(4)]
    pts = torch.randn(2, 1 + 3 * 4, 3)
    assert torch.equal(subsample(pts, 3, 2), pts[:, [0, 2, 4, 6, 8, 10, 12]])
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="points_per_segment"):
            body_layout(spec, bad)


def test_models_without_a_body_say_so():
    spec = RobotSpec.from_yaml(ROBOTS / "tdcr_3seg_coupled.yaml")
    q = generate(spec, 4, seed=0)["q"]
    with pytest.raises(ValueError, match="has no body.*twist"):
        CompositionalFK(spec, rotation="6d").body(q)
    with pytest.raises(ValueError, match="has no body.*body_points"):
        FKModel(spec).body(q)
    with pytest.raises(ValueError, match="has no body"):
        as_solver_model(FKModel(spec).double()).body(torch.zeros(2, spec.num_actuated_features, dtype=F64))
    with pytest.raises(ValueError, match="body_points"):
        FKModel(spec, body_points=-1)


def test_the_shape_output_of_an_fk_network():
    """A separate shape network: (B, 1 + m·K, 3) from the base origin, divisors of K by subsampling; the tip network
    and the state dict without it unchanged."""
    spec = RobotSpec.from_yaml(ROBOTS / "tdcr_3seg_coupled.yaml")
    q = generate(spec, 5, seed=0)["q"]
    torch.manual_seed(0)
    plain = FKModel(spec, width=16, depth=2)
    torch.manual_seed(0)
    shaped = FKModel(spec, width=16, depth=2, body_points=4)
    assert set(shaped.state_dict()) - set(plain.state_dict()) == {k for k in shaped.state_dict() if "body_net" in k}
    assert torch.equal(plain(q), shaped(q))
    body = shaped.body(q)
    assert body.points.shape == (5, 13, 3) and bool((body.points[:, 0] == 0).all())
    assert torch.equal(shaped.body(q, 2).points, subsample(body.points, 3, 2))
    with pytest.raises(ValueError, match="divisor"):
        shaped.body(q, 3)


def test_the_datamodule_serves_the_true_body():
    """CC: the exact arcs of the features; Cosserat: every (steps/K)-th node of the rod, which is the solver's own
    frames at those arcs (its last point the tip)."""
    spec = ROBOTS / "tdcr_3seg_coupled.yaml"
    dm = KinematicsDataModule(str(spec), n_train=16, n_val=8, n_test=8, batch_size=8, body_points=4)
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["backbone"].shape == (8, 13, 3)
    train = dm.splits["train"]
    assert torch.allclose(train["backbone"], cc_body(dm.spec, train["features"], 4).points)
    plain = KinematicsDataModule(str(spec), n_train=16, n_val=8, n_test=8, batch_size=8)
    plain.setup()
    assert "backbone" not in next(iter(plain.train_dataloader()))


@pytest.fixture(scope="module")
def cosserat_samples():
    spec = RobotSpec.from_yaml(ROBOTS / "tdcr_3seg_cosserat.yaml")
    options = cosserat_data.CosseratOptions(steps_per_segment=4)
    return spec, options, cosserat_data.generate(spec, 6, seed=0, options=options, dtype=F64, progress=False)


def test_the_cosserat_body_is_the_rods_nodes(cosserat_samples):
    spec, options, data = cosserat_samples
    sol = solve_statics(spec, data["tension"], gravity=torch.tensor(options.gravity, dtype=F64), steps_per_segment=4,
                        tol=options.tol, max_iter=options.max_iter)
    body = sol.body(spec)
    assert torch.allclose(body.points, data["backbone"], rtol=0, atol=1e-12)
    assert torch.allclose(body.points[:, -1], data["pose"][:, :3, 3], rtol=0, atol=1e-12)
    assert torch.equal(sol.body(spec, 2).points, subsample(body.points, 3, 2))
    with pytest.raises(ValueError, match="divisor"):
        sol.body(spec, 3)
    # no load: a straight rod along z, each node at its reference arc length
    straight = solve_statics(spec, torch.zeros(1, spec.num_joints, dtype=F64), steps_per_segment=4).body(spec)
    along_z = torch.nn.functional.pad(straight.arc_length.unsqueeze(-1), (2, 0))
    assert torch.allclose(straight.points[0], along_z, rtol=0, atol=1e-12)


def test_fk_training_on_the_data_body(tmp_path):
    """A few steps of FKModule with the shape loss on served backbones: the loss and the summary see the body."""
    spec = ROBOTS / "tdcr_3seg_coupled.yaml"
    dm = KinematicsDataModule(str(spec), n_train=64, n_val=16, n_test=16, batch_size=16, body_points=2)
    for structure, rotation, k in (("monolithic", "6d", 2), ("compositional", "twist", 0)):
        module = FKModule(str(spec), width=16, depth=1, structure=structure, rotation=rotation, body_points=k,
                          body_weight=1.0)
        trainer = pl.Trainer(max_epochs=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                             enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
        trainer.fit(module, dm)
        trainer.test(module, dm, verbose=False)
        assert module.test_summary["body_err_mean_mm"] > 0
        if k:                                           # the Rerun scene draws the shape output as the learned body
            assert module.visual_batch()["backbone_pred"].shape == (8, 1 + 3 * k, 3)
        batch = next(iter(dm.train_dataloader()))
        tip_only = module.pose_loss(module.model(batch["q"]), batch["pose"])
        assert module.loss(batch).item() > tip_only.item()


def test_the_solver_adapters_give_the_body():
    spec = RobotSpec.from_yaml(ROBOTS / "type3.yaml")
    data = generate(spec, 8, seed=1, dtype=F64)
    cc = as_solver_model(spec)
    x = cc.variables(data["q"])
    body = cc.body(x, 5)
    assert isinstance(body, BodyPoints)
    assert torch.allclose(body.points, cc_body(spec, data["features"], 5).points, rtol=0, atol=1e-14)
    assert torch.allclose(body.points[:, -1], forward_kinematics(spec, data["features"])[:, :3, 3], atol=1e-14)
    learned = as_solver_model(exact_compositional(spec, data["q"]))
    assert torch.allclose(learned.body(x, 5).points, body.points, rtol=0, atol=1e-13)


def test_a_hardware_model_has_its_calibrated_body():
    """The saved model's body is the calibrated CC model's arcs in the motion-capture frame: they start at the
    fitted base and end where the CC tip frame is (the marker offset d = 0 gives the tip itself)."""
    from hardware_testkit import synthetic_model

    from dacr_learn.hardware.deploy.ik import HardwareTip

    model = synthetic_model(history=False, members=1)
    servo = 1e3 * torch.linspace(-2e-3, 2e-3, 8 * 6, dtype=F64).reshape(6, 8)
    body = HardwareTip(model).body(servo, 6)
    cc = model.cc
    x = model.smap.command_displacements(model.spec, model.servo_ids, 1e-3 * servo)
    with torch.no_grad():
        tip = cc.to_world(forward_kinematics(model.spec, cc.encoder(x))[:, :3, 3])
        base = cc.to_world(torch.zeros(3, dtype=F64))
    assert body.points.shape == (6, 1 + 6 * model.spec.num_segments, 3)
    assert torch.allclose(body.points[:, -1], tip, rtol=0, atol=1e-14)
    assert torch.allclose(body.points[:, 0], base.expand(6, 3), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="servo_mm"):
        model.body(servo[:, :3])


def test_the_weightless_calibrated_rod_has_the_calibrated_cc_body():
    """With no weight and an inextensible backbone the rod is the CC model (as its tip is): its nodes lie on the CC
    arcs to micrometres at every point, in the motion-capture frame."""
    from hardware_testkit import LABELLED_IDS, LABELLED_ROBOT, labelled_servo_map

    from dacr_learn.hardware.ccmodel import CalibratedCC
    from dacr_learn.hardware.cosserat_model import CalibratedCosserat
    from dacr_learn.hardware.learned import synthetic_split

    cc = CalibratedCC(RobotSpec.from_dict(LABELLED_ROBOT), compliance=2e-6)
    with torch.no_grad():
        cc.encoder.rotation.copy_(torch.tensor([0.03, -0.05]))
        cc.base_tilt.copy_(torch.tensor([0.02, -0.01]))
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005]))
    cc.requires_grad_(False)
    x = synthetic_split(cc, labelled_servo_map(cc.spec), LABELLED_IDS, 12, 0).x
    rod = CalibratedCosserat(cc, axial_radius=1e-5)
    body = rod.body(x)
    assert body.points.shape[-2] == 1 + rod.steps * cc.spec.num_segments
    with torch.no_grad():
        reference = cc.body(x, rod.steps)
    assert float((body.points - reference.points).norm(dim=-1).max()) < 5e-6
    assert torch.equal(body.arc_length, reference.arc_length)


def test_a_shape_output_with_the_cc_prior_starts_at_the_cc_arcs():
    """body_prior "cc": the network gives offsets from the CC arcs of the joints' Clarke features, zero at the start."""
    spec = RobotSpec.from_yaml(ROBOTS / "type3.yaml")
    data = generate(spec, 6, seed=2, dtype=F64)
    model = FKModel(spec, width=16, depth=2, body_points=4, body_prior="cc").to(F64)
    model.fit_normalization(data["q"])
    assert torch.allclose(model.body(data["q"]).points, cc_body(spec, data["features"], 4).points, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="body_prior"):
        FKModel(spec, body_points=4, body_prior="arc")


def test_a_denser_request_gets_the_shape_outputs_own_points_and_the_scene_check_runs():
    """A shape output of K = 4 points per segment asked for 32 (the clearance check's count) or 3 serves the largest
    divisor of K not above the request (4, 2); the scene check of such a model (a CC-prior network at its start, so
    the CC arcs) is a lower bound of the dense clearance of the same arcs."""
    from dacr_learn.ik.collision import Avoidance
    from dacr_learn.scene import load_scene
    spec = RobotSpec.from_yaml(ROBOTS / "type3.yaml")
    data = generate(spec, 5, seed=3, dtype=F64)
    model = FKModel(spec, width=16, depth=2, body_points=4, body_prior="cc").to(F64)
    model.fit_normalization(data["q"])
    adapter = as_solver_model(model)
    x = adapter.variables(data["q"])
    for asked, served in ((32, 4), (3, 2), (1, 1)):
        got = adapter.body(x, asked)
        assert got.points.shape[1] == 1 + spec.num_segments * served
        assert torch.allclose(got.points, cc_body(spec, data["features"], served).points, rtol=0, atol=1e-12)
    centre = cc_body(spec, data["features"][:1], 4).points[0, -1] + torch.tensor([0.02, 0.0, 0.0], dtype=F64)
    scene = load_scene({"obstacles": [{"type": "sphere", "center": centre.tolist(), "radius": 0.005}]})
    bound = Avoidance(adapter, scene, 0.0).clearance_of_joints(data["q"])
    dense = cc_body(spec, data["features"], 256)
    exact = ((dense.points - centre).norm(dim=-1) - 0.005 - dense.radius).amin(-1)
    assert torch.isfinite(bound).all() and (bound <= exact + 1e-12).all()
