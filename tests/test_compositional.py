"""Compositional FK: composition against the CC kinematics, transfer, checkpoints and export.

The composition tests set the per-segment network to the exact CC map (a CC arc is the exp of
the twist (0, 0, β, −ρ_im/d, ρ_re/d, 0), linear in the features) and compare the composed frames
with kinematics.segment_tip_poses / forward_kinematics: a wrong product order, a transposed
factor or a wrong head fails them.
"""
from __future__ import annotations

import os

import lightning
import pytest
import torch
from conftest import TDCR3, roundoff_tol

from dacr_learn import export as dexport
from dacr_learn.compositional import CompositionalFK, build_fk_model, transfer
from dacr_learn.control import ResolvedRateController
from dacr_learn.data import generate
from dacr_learn.kinematics import forward_kinematics, segment_tip_poses
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
SEGMENT = {"type": "I", "length": 0.1, "radius": 0.008, "joints": 4, "limits": {"bend": 1.2, "length": [0.09, 0.11]}}


def equal_segments(m: int, joints: int = 4) -> RobotSpec:
    segs = [{**SEGMENT, "joints": joints, "offset": 0.3 * k} for k in range(m)]
    return RobotSpec.from_dict({"name": f"equal{m}", "routing": "coupled", "segments": segs})


def exact_cc_model(spec: RobotSpec, context: str = "none") -> CompositionalFK:
    """A float64 CompositionalFK whose network is the exact CC twist map (all type I/0, one radius)."""
    model = CompositionalFK(spec, width=8, depth=1, context=context).to(F64)
    model.fit_normalization(generate(spec, 512, seed=0, dtype=F64)["q"])
    d, ls = spec.segments[0].radius, model.length_scale.item()
    a = torch.zeros(6, 4, dtype=F64)                                  # twist = A · (ρ_re, ρ_im, β, α)
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
        if not name.startswith("front.encoder.") and name != "front.context_matrix":
            assert torch.equal(moved.state_dict()[name], value), name


def test_transfer_refuses_segment_context_and_unknown_geometry():
    with pytest.raises(ValueError, match="segment"):
        transfer(CompositionalFK(equal_segments(2), context="segment"), equal_segments(3))
    with pytest.raises(ValueError, match="geometry"):
        transfer(CompositionalFK(equal_segments(2)), TDCR3)


# ------------------------------------------------------------------------------------------
# Checkpoint and export


def _checkpoint(module: FKModule, path):
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": lightning.__version__}, path)
    return path


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A compositional FKModule trained for a few steps, and its checkpoint."""
    torch.manual_seed(0)
    module = FKModule(robot=TDCR3.to_dict(), structure="compositional", context="distal", rotation="twist",
                      width=16, depth=2, rot_weight=0.1)
    data = generate(TDCR3, 512, seed=9)
    module.model.fit_normalization(data["q"])
    opt = torch.optim.Adam(module.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss = module.loss({"q": data["q"], "pose": data["pose"]})
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    return module.eval(), _checkpoint(module, tmp_path_factory.mktemp("ckpt") / "comp.ckpt")


def test_checkpoint_round_trip(trained):
    module, path = trained
    loaded = FKModule.load_from_checkpoint(path, map_location="cpu").eval()
    assert isinstance(loaded.model, CompositionalFK) and loaded.model.front.context == "distal"
    q = generate(TDCR3, 32, seed=10)["q"]
    with torch.no_grad():
        assert torch.equal(loaded(q), module(q))


def test_export_round_trip(trained, tmp_path):
    module, path = trained
    aoti = os.environ.get("DACR_TEST_AOTI") == "1"
    meta = dexport.export_checkpoint(path, tmp_path, aoti=aoti)
    assert set(meta["modules"]) == {"fk", "jacobian"} and meta.get("structure") == "compositional"
    loaded = dexport.load(tmp_path, "fk")
    q = generate(TDCR3, 40, seed=12)["q"]
    with torch.no_grad():
        assert torch.allclose(loaded(q.reshape(4, 10, -1)).reshape(40, 4, 4), module(q), rtol=0,
                              atol=dexport.VERIFY_TOLERANCE)
    pose, jac_f, jac_q = dexport.load(tmp_path, "jacobian")(q[:3])
    assert jac_f.shape == (3, 6, TDCR3.num_actuated_features) and jac_q.shape == (3, 6, TDCR3.num_joints)
    assert torch.allclose(pose, module(q[:3]), rtol=0, atol=dexport.VERIFY_TOLERANCE)
    controller = ResolvedRateController(TDCR3, dexport.load(tmp_path, "jacobian"))   # drives a controller
    target = module(q[:1])[0, :3, 3] + torch.tensor([0.002, -0.001, 0.0])
    command = q[:1].double()
    for _ in range(30):
        command = controller.step(command, target)
    with torch.no_grad():
        assert float((module(command.float())[0, :3, 3] - target).norm()) < 2e-4
