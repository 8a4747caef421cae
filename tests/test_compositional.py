"""Compositional FK: exp head and composition against the CC kinematics, folding/export, transfer,
checkpoints, the combination-regime sampling and the segment-frame targets.

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
from conftest import roundoff_tol, spec_by_name

from dacr_learn import export as dexport
from dacr_learn.combination_shift import combination_split, summarize_rows
from dacr_learn.compositional import CompositionalFK, build_fk_model, transfer, twist_exp
from dacr_learn.data import bending_subsets, generate
from dacr_learn.inference_compositional import InferenceCompositionalFK
from dacr_learn.kinematics import cc_transform, forward_kinematics, segment_tip_poses
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
TDCR3 = spec_by_name("tdcr_3seg_coupled")
SEGMENT = {"type": "I", "length": 0.1, "radius": 0.008, "joints": 4, "limits": {"bend": 1.2, "length": [0.09, 0.11]}}


def equal_segments(m: int, joints: int = 4) -> RobotSpec:
    segs = [{**SEGMENT, "joints": joints, "offset": 0.3 * k} for k in range(m)]
    return RobotSpec.from_dict({"name": f"equal{m}", "routing": "coupled", "segments": segs})


def hat(xi: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    v, w = xi[..., :3], xi[..., 3:]
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    out[..., :3, 3] = v
    return out


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
# exp head


@pytest.mark.parametrize("scale", [0.0, 1e-4, 0.05, 0.3, 1.0, 3.0])
def test_twist_exp_equals_matrix_exp(scale):
    g = torch.Generator().manual_seed(1)
    xi = torch.randn(200, 6, generator=g, dtype=F64)
    xi[:, 3:] *= scale
    assert torch.allclose(twist_exp(xi), torch.linalg.matrix_exp(hat(xi)), rtol=0, atol=roundoff_tol(F64, 10.0))


def test_twist_exp_of_cc_twist_is_the_cc_arc():
    g = torch.Generator().manual_seed(2)
    u, beta = torch.randn(100, 2, generator=g, dtype=F64), 0.05 + torch.rand(100, generator=g, dtype=F64)
    xi = torch.stack([0 * beta, 0 * beta, beta, -u[:, 1], u[:, 0], 0 * beta], dim=-1)
    assert torch.allclose(twist_exp(xi), cc_transform(u, beta), rtol=0, atol=roundoff_tol(F64))


@pytest.mark.parametrize("scale", [0.0, 0.05, 1.0])       # 0 and 0.05: the Taylor branch of g
def test_twist_exp_gradcheck(scale):
    xi = (torch.randn(4, 6, generator=torch.Generator().manual_seed(3), dtype=F64) * scale).requires_grad_()
    assert torch.autograd.gradcheck(twist_exp, (xi,))


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
# Data: combination regimes and segment frames


def test_bending_subsets():
    masks = bending_subsets(3, 2)
    assert masks.shape == (7, 3) and set(map(tuple, masks.tolist())) == {
        (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1)}
    with pytest.raises(ValueError, match="max_bending"):
        bending_subsets(3, 4)


def test_generate_with_max_bending_and_segment_frames():
    data = generate(TDCR3, 2000, seed=7, max_bending=2, segment_frames=True)
    bending = data["features"][..., :2].abs().sum(-1) > 0                       # (N, m)
    assert int(bending.sum(-1).max()) == 2
    assert len({tuple(b) for b in bending.tolist()}) == 7                        # every subset occurs
    assert bool((data["features"][..., 2] > 0).all())                           # β still sampled
    assert torch.allclose(data["segment_frames"][:, -1], data["pose_clean"], rtol=0, atol=1e-6)
    assert torch.equal(generate(TDCR3, 50, seed=7)["q"], generate(TDCR3, 50, seed=7, segment_frames=True)["q"])


def test_segment_frames_enter_the_loss_only_when_weighted():
    data = generate(TDCR3, 64, seed=8, segment_frames=True)
    batch = {k: data[k] for k in ("q", "pose", "segment_frames")}
    torch.manual_seed(0)
    module = FKModule(robot=TDCR3.to_dict(), structure="compositional", rotation="twist", width=8, depth=1,
                      segment_weight=1.0)
    module.model.fit_normalization(data["q"])
    with_frames = module.loss(batch)
    tip_only = module.loss({"q": batch["q"], "pose": batch["pose"]})
    assert with_frames > tip_only > 0


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


@pytest.mark.parametrize("robot,context,rotation", [("tdcr_3seg_coupled", "none", "twist"),
                                                    ("tdcr_3seg_coupled", "segment", "6d"),
                                                    ("type3", "distal", "twist"), ("twisting", "none", "6d")])
def test_folded_equals_model_float64(robot, context, rotation):
    spec = spec_by_name(robot)
    torch.manual_seed(2)
    model = CompositionalFK(spec, width=8, depth=2, rotation=rotation, context=context).to(F64)
    q = generate(spec, 64, seed=11, dtype=F64)["q"]
    model.fit_normalization(q)
    folded = InferenceCompositionalFK(model, F64)
    with torch.no_grad():
        assert torch.allclose(folded(q), model(q), rtol=0, atol=roundoff_tol(F64, spec.total_length, ulps=4096))


def test_export_round_trip(trained, tmp_path):
    module, path = trained
    aoti = os.environ.get("DACR_TEST_AOTI") == "1"
    meta = dexport.export_checkpoint(path, tmp_path, aoti=aoti)
    assert set(meta["modules"]) == {"fk"} and meta.get("structure") == "compositional"
    loaded = dexport.load(tmp_path, "fk")
    q = generate(TDCR3, 40, seed=12)["q"]
    with torch.no_grad():
        assert torch.allclose(loaded(q.reshape(4, 10, -1)).reshape(40, 4, 4), module(q), rtol=0,
                              atol=dexport.VERIFY_TOLERANCE)


# ------------------------------------------------------------------------------------------
# Combination-shift study (library functions; the study itself is a script)


def test_combination_split_regimes():
    split = combination_split(TDCR3, 300, 200, seed=0, max_bending=2)
    bends = {k: (v["features"][..., :2].abs().sum(-1) > 0).sum(-1) for k, v in split.items()}
    assert int(bends["train"].max()) <= 2 and int(bends["heldout"].max()) <= 2
    assert bool((bends["all_bending"] == 3).all())
    assert not torch.equal(split["train"]["q"][:200], split["heldout"]["q"])
    with pytest.raises(ValueError, match="max_bending"):
        combination_split(TDCR3, 10, 10, seed=0, max_bending=3)


def test_summary_reports_mean_std_and_ratio():
    rows = [{"study": "shift", "model": "c", "seed": s, "test": t, "pos_err_mean_mm": e, "pos_err_mean_pct": e,
             "rot_err_mean_deg": 2 * e} for s, (t, e) in enumerate([("heldout", 1.0), ("heldout", 3.0),
                                                                   ("all_bending", 4.0), ("all_bending", 4.0)])]
    s = summarize_rows(rows)["shift/c"]
    assert s["heldout"]["pos_err_mean_mm"] == pytest.approx(2.0)
    assert s["heldout"]["pos_err_mean_mm_std"] == pytest.approx(2 ** 0.5)
    assert s["ratio_all_bending_to_heldout"]["pos_err_mean_mm"] == pytest.approx(2.0)
