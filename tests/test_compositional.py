"""Compositional FK: composition against the CC kinematics, transfer, checkpoints and export.

The composition tests set the per-segment network to the exact CC map (a CC arc is the exp of
the twist (0, 0, β, −ρ_im/d, ρ_re/d, 0), linear in the features) and compare the composed frames
with kinematics.segment_tip_poses / forward_kinematics: a wrong product order, a transposed
factor or a wrong head fails them.
"""
from __future__ import annotations

import os
import shutil

import pytest
import torch
from conftest import TDCR3, first_pass_export, roundoff_tol, save_small_checkpoint, spec_by_name

from dacr_learn import export as dexport
from dacr_learn.compositional import ROBOT_BUFFERS, CompositionalFK, build_fk_model, transfer
from dacr_learn.data import generate
from dacr_learn.deploy.control import ResolvedRateController
from dacr_learn.kinematics import forward_kinematics, segment_tip_poses
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
SEGMENT = {"type": "I", "length": 0.1, "radius": 0.008, "joints": 4, "limits": {"bend": 1.2, "length": [0.09, 0.11]}}


def equal_segments(m: int, joints: int = 4) -> RobotSpec:
    segs = [{**SEGMENT, "joints": joints, "offset": 0.3 * k} for k in range(m)]
    return RobotSpec.from_dict({"name": f"equal{m}", "routing": "coupled", "segments": segs})


def exact_cc_model(spec: RobotSpec, context: str = "none", units: str = "strain", twist_roll: bool = True
                   ) -> CompositionalFK:
    """A float64 CompositionalFK whose network is the exact CC twist map ("metric": one radius).

    "strain": x = (ρ_re/d, ρ_im/d, β/l, α) and the translation is scaled by l, so the map is the same for
    every segment: ξ = (0, 0, x₃; −x₂, x₁, 0). "metric": x = (ρ, β, α), translation scaled by L_s. A twisting
    segment (types II/III) is exact because the model rolls it by α first (Rz(α)·exp(ξ), ``twist_roll``)."""
    model = CompositionalFK(spec, width=8, depth=1, context=context, units=units, twist_roll=twist_roll).to(F64)
    model.fit_normalization(generate(spec, 512, seed=0, dtype=F64)["q"])
    d, ls = (1.0, 1.0) if units == "strain" else (spec.segments[0].radius, model.length_scale[0].item())
    a = torch.zeros(6, 4, dtype=F64)                                  # twist = A · x
    a[2, 2], a[3, 1], a[4, 0] = 1 / ls, -1 / d, 1 / d
    mean, std = model.front.norm.mean, model.front.norm.std
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
        model.skip.weight.zero_()
        model.skip.weight[:, :4] = a * std
        model.net[-1].bias.copy_(a @ mean)
    return model


# ------------------------------------------------------------------------------------------
# Composition


@pytest.mark.parametrize("context", ["none", "distal"])
def test_composed_frames_equal_cc_kinematics(context):
    model = exact_cc_model(TDCR3, context)
    data = generate(TDCR3, 300, seed=4, dtype=F64)
    ends = model.segment_ends(data["q"])
    tol = roundoff_tol(F64, TDCR3.total_length, ulps=4096)           # float64 encoder solve + 3 products
    assert torch.allclose(ends, segment_tip_poses(TDCR3, data["features"]), rtol=0, atol=tol)
    assert torch.allclose(model(data["q"]), forward_kinematics(TDCR3, data["features"]), rtol=0, atol=tol)


HETERO = ["hetero_2seg_coupled", "hetero_3seg_coupled", "hetero_5seg_coupled"]   # types 0/I (exact twist map)


@pytest.mark.parametrize("robot", [*HETERO, "hetero_4seg_types", "type3", "twisting"])
def test_strain_units_make_one_exact_map_for_every_segment_geometry(robot):
    """In strain units the exact CC map is the same for segments of any length, radius, type and joint layout:
    one network (set to it) reproduces every segment end of a robot whose segments all differ."""
    spec = spec_by_name(robot)
    assert len({(s.length, s.radius, s.num_joints) for s in spec.segments}) == spec.num_segments
    data = generate(spec, 300, seed=4, dtype=F64)
    ends = exact_cc_model(spec).segment_ends(data["q"])
    tol = roundoff_tol(F64, spec.total_length, ulps=4096)
    assert torch.allclose(ends, segment_tip_poses(spec, data["features"]), rtol=0, atol=tol)


@pytest.mark.parametrize("robot", ["hetero_4seg_types", "type3", "twisting"])
def test_a_twisting_segment_is_exact_only_when_rolled_first(robot):
    """Rz(α)·T_cc is the exp of a linear twist only in the rolled frame: the same exact map without the roll
    misses the CC kinematics of a twisting robot by millimetres (the map a network had to learn before)."""
    spec = spec_by_name(robot)
    data = generate(spec, 300, seed=4, dtype=F64)
    truth = forward_kinematics(spec, data["features"])
    rolled, plain = exact_cc_model(spec), exact_cc_model(spec, twist_roll=False)
    assert rolled.roll.tolist() == [s.twists for s in spec.segments] and not plain.roll.any()
    assert torch.allclose(rolled(data["q"]), truth, rtol=0, atol=roundoff_tol(F64, spec.total_length, ulps=4096))
    err = (plain(data["q"])[:, :3, 3] - truth[:, :3, 3]).norm(dim=-1)
    assert err.mean() > 1e-3 * spec.total_length


@pytest.mark.parametrize("context", ["none", "distal", "full"])
def test_the_untrained_network_does_not_depend_on_a_rolled_segments_alpha(context):
    """With a rolled segment the α inputs start at zero weight: changing α_k alone (same ρ, β) turns T_k into
    Rz(Δα_k)·T_k and leaves every other segment's transform as it was."""
    spec = spec_by_name("hetero_4seg_types")
    torch.manual_seed(0)
    model = CompositionalFK(spec, width=16, depth=2, context=context).to(F64)
    data = generate(spec, 64, seed=3, dtype=F64)
    model.fit_normalization(data["q"])
    delta = torch.tensor([0.0, 0.0, 0.3, -0.5], dtype=F64)
    moved = data["features"] + torch.cat([torch.zeros(4, 3, dtype=F64), delta.unsqueeze(-1)], -1)
    with torch.no_grad():
        before = model.segment_transforms(data["q"])
        after = model.segment_transforms(ClarkeDecoder(spec).to(F64)(moved))
    c, s = torch.cos(delta), torch.sin(delta)
    rz = torch.eye(4, dtype=F64).repeat(4, 1, 1)
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c, -s, s, c
    torch.testing.assert_close(after, rz @ before, rtol=0, atol=1e-12)


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "hetero_5seg_coupled"])
def test_the_roll_leaves_a_robot_that_does_not_twist_unchanged(robot):
    """Same seed, with and without the roll: identical parameters and bit-identical outputs (float32)."""
    spec = spec_by_name(robot)
    torch.manual_seed(0)
    rolled = CompositionalFK(spec, width=16, depth=2)
    torch.manual_seed(0)
    plain = CompositionalFK(spec, width=16, depth=2, twist_roll=False)
    assert not rolled.rolls and rolled.state_dict().keys() == plain.state_dict().keys()
    for name, value in rolled.state_dict().items():
        assert torch.equal(plain.state_dict()[name], value), name
    q = generate(spec, 64, seed=3)["q"]
    rolled.fit_normalization(q)
    plain.fit_normalization(q)
    with torch.no_grad():
        assert torch.equal(rolled(q), plain(q))


def test_a_state_dict_from_before_the_roll_loads_without_it():
    """A twisting robot's state dict without the ``roll`` buffer is a model of the earlier head (no roll)."""
    spec = spec_by_name("hetero_4seg_types")
    torch.manual_seed(0)
    plain = CompositionalFK(spec, width=8, depth=2, twist_roll=False)
    plain.fit_normalization(generate(spec, 64, seed=3)["q"])
    old = {k: v for k, v in plain.state_dict().items() if k != "roll"}
    fresh = CompositionalFK(spec, width=8, depth=2)
    fresh.load_state_dict(old)
    assert not fresh.rolls and not fresh.roll.any()
    q = generate(spec, 16, seed=1)["q"]
    with torch.no_grad():
        assert torch.equal(fresh(q), plain(q))


def test_metric_units_cannot_share_one_map_across_radii():
    """The failure strain units fix: in metric units the exact map for one radius is wrong for another."""
    spec = spec_by_name("hetero_3seg_coupled")
    model = exact_cc_model(RobotSpec.from_dict({**spec.to_dict(), "segments": [
        {**s.to_dict(), "radius": spec.segments[0].radius} for s in spec.segments]}), units="metric")
    moved = CompositionalFK(spec, width=8, depth=1, units="metric").to(F64)
    moved.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("front.encoder.")},
                          strict=False)
    data = generate(spec, 100, seed=4, dtype=F64)
    err = (moved(data["q"])[:, :3, 3] - forward_kinematics(spec, data["features"])[:, :3, 3]).norm(dim=-1)
    assert err.mean() > 1e-3 * spec.total_length


@pytest.mark.parametrize("source,target", [("hetero_3seg_coupled", "hetero_5seg_coupled"),
                                           ("hetero_5seg_coupled", "hetero_2seg_coupled"),
                                           ("type3", "hetero_4seg_types"), ("hetero_4seg_types", "twisting")])
def test_transfer_in_strain_units_runs_any_geometry(source, target):
    moved = transfer(exact_cc_model(spec_by_name(source)), spec_by_name(target))
    spec = spec_by_name(target)
    data = generate(spec, 200, seed=6, dtype=F64)
    tol = roundoff_tol(F64, spec.total_length, ulps=4096)
    assert torch.allclose(moved.segment_ends(data["q"]), segment_tip_poses(spec, data["features"]), rtol=0, atol=tol)


def test_old_metric_state_dict_loads():
    """A state dict from before the units option (scalar length_scale, no front.unit) loads as a metric model."""
    torch.manual_seed(0)
    model = CompositionalFK(TDCR3, width=8, depth=2, units="metric")
    old = {k: v for k, v in model.state_dict().items() if k != "front.unit"}
    old["length_scale"] = model.length_scale[0].float().clone()
    fresh = CompositionalFK(TDCR3, width=8, depth=2)              # default strain units, overwritten by the load
    fresh.load_state_dict(old)
    assert fresh.units == "metric"
    q = generate(TDCR3, 16, seed=1)["q"]
    with torch.no_grad():
        assert torch.allclose(fresh(q), model(q), rtol=0, atol=roundoff_tol(torch.float32, TDCR3.total_length))


def test_batched_equals_per_sample_float32():
    torch.manual_seed(0)
    model = CompositionalFK(TDCR3, width=16, depth=2, context="distal")
    q = generate(TDCR3, 16, seed=5)["q"]
    model.fit_normalization(q)
    batched = model(q.reshape(4, 4, -1)).reshape(16, 4, 4)
    single = torch.stack([model(x) for x in q])
    assert torch.allclose(batched, single, rtol=0, atol=roundoff_tol(torch.float32, 1.0))


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="features"):
        CompositionalFK(TDCR3, features="raw")
    with pytest.raises(ValueError, match="rotation"):
        CompositionalFK(TDCR3, rotation="quaternion")
    with pytest.raises(ValueError, match="context"):
        CompositionalFK(TDCR3, context="proximal")
    with pytest.raises(ValueError, match="extra_inputs"):
        CompositionalFK(TDCR3, extra_inputs=-1)
    with pytest.raises(ValueError, match="structure"):
        build_fk_model(TDCR3, "modular")
    with pytest.raises(ValueError, match="context"):
        build_fk_model(TDCR3, "monolithic", "distal")
    with pytest.raises(ValueError, match="joint vector"):
        CompositionalFK(TDCR3)(torch.zeros(3, 5))


# ------------------------------------------------------------------------------------------
# Transfer


def test_transfer_two_to_three_segments_is_exact_for_the_exact_map():
    two, three = equal_segments(2), equal_segments(3, joints=6)
    moved = transfer(exact_cc_model(two), three)
    data = generate(three, 200, seed=6, dtype=F64)
    tol = roundoff_tol(F64, three.total_length, ulps=4096)
    assert torch.allclose(moved.segment_ends(data["q"]), segment_tip_poses(three, data["features"]), rtol=0, atol=tol)


def test_transfer_keeps_the_network_unchanged():
    torch.manual_seed(1)
    source = CompositionalFK(equal_segments(2), width=8, depth=2)
    moved = transfer(source, equal_segments(3))
    for name, value in source.state_dict().items():
        if not name.startswith(ROBOT_BUFFERS):
            assert torch.equal(moved.state_dict()[name], value), name


def test_transfer_refuses_segment_context_and_unknown_geometry():
    with pytest.raises(ValueError, match="segment"):
        transfer(CompositionalFK(equal_segments(2), context="segment"), equal_segments(3))
    with pytest.raises(ValueError, match="context 'full'"):
        transfer(CompositionalFK(equal_segments(2), context="full"), equal_segments(3))
    with pytest.raises(ValueError, match="geometry"):
        transfer(CompositionalFK(equal_segments(2), units="metric"), TDCR3)


# ------------------------------------------------------------------------------------------
# Checkpoint and export


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A compositional FKModule trained for a few steps, and its checkpoint (conftest.save_small_checkpoint, which
    fits the normalisation to 2,048 samples of seed 0 again: the statistics it was trained with)."""
    torch.manual_seed(0)
    module = FKModule(robot=TDCR3.to_dict(), structure="compositional", context="distal", rotation="twist",
                      width=16, depth=2, rot_weight=0.1)
    data = generate(TDCR3, 512, seed=9)
    module.model.fit_normalization(generate(TDCR3, 2048, seed=0)["q"])
    opt = torch.optim.Adam(module.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss = module.loss({"q": data["q"], "pose": data["pose"]})
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    path = tmp_path_factory.mktemp("ckpt") / "comp.ckpt"
    save_small_checkpoint(module, path)
    return module.eval(), path


def test_checkpoint_round_trip(trained):
    module, path = trained
    loaded = FKModule.load_from_checkpoint(path, map_location="cpu").eval()
    assert isinstance(loaded.model, CompositionalFK) and loaded.model.front.context == "distal"
    q = generate(TDCR3, 32, seed=10)["q"]
    with torch.no_grad():
        assert torch.equal(loaded(q), module(q))


def test_export_round_trip(trained, tmp_path_factory):
    """The trained model's checkpoint exported (conftest.first_pass_export: under make test the second pass runs the
    first pass's export) equals the model loaded from that checkpoint and drives a controller."""
    aoti = os.environ.get("DACR_TEST_AOTI") == "1"

    def make(out):
        shutil.copy(trained[1], out / "comp.ckpt")
        return dexport.export_checkpoint(out / "comp.ckpt", out / "export", aoti=aoti)

    root, meta = first_pass_export("compositional_fk", make, tmp_path_factory)
    module, tmp_path = FKModule.load_from_checkpoint(root / "comp.ckpt", map_location="cpu").eval(), root / "export"
    assert set(meta["modules"]) == {"fk", "jacobian"} and meta.get("structure") == "compositional"
    loaded = dexport.load(tmp_path, "fk")
    q = generate(TDCR3, 40, seed=12)["q"]
    with torch.no_grad():
        assert torch.allclose(loaded(q.reshape(4, 10, -1)).reshape(40, 4, 4), module(q), rtol=0,
                              atol=dexport.VERIFY_TOLERANCE)
    jacobian = dexport.load(tmp_path, "jacobian")                   # loaded once (a load takes seconds)
    pose, jac_f, jac_q = jacobian(q[:3])
    assert jac_f.shape == (3, 6, TDCR3.num_actuated_features) and jac_q.shape == (3, 6, TDCR3.num_joints)
    assert torch.allclose(pose, module(q[:3]), rtol=0, atol=dexport.VERIFY_TOLERANCE)
    controller = ResolvedRateController(TDCR3, jacobian)                            # drives a controller
    target = module(q[:1])[0, :3, 3] + torch.tensor([0.002, -0.001, 0.0])
    command = q[:1].double()
    for _ in range(30):
        command = controller.step(command, target)
    with torch.no_grad():
        assert float((module(command.float())[0, :3, 3] - target).norm()) < 2e-4


def test_transfer_refuses_a_feature_the_source_never_varied():
    with pytest.raises(ValueError, match=r"segments \[2, 3\] of 'hetero-4seg-types' twist"):
        transfer(CompositionalFK(spec_by_name("hetero_3seg_coupled")), spec_by_name("hetero_4seg_types"))
    type0 = RobotSpec.from_dict({"name": "t0", "routing": "independent", "segments": [
        {"type": "0", "length": 0.1, "radius": 0.008, "joints": 4}]})
    with pytest.raises(ValueError, match="extend"):
        transfer(CompositionalFK(type0), TDCR3)
