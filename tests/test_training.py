"""dacr_learn.training: IK with a pose-space loss (IKModule feature_weight / pose_weight / limit_weight): the decoded
features, the loss at a true solution, the joint-limit penalty, gradients in float64, and bad weights; the one-cycle
learning-rate schedule; the segment-frame loss of the compositional FKModule."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from conftest import ROOT, TDCR3

from dacr_learn.data import generate
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.models import pose_to_vector
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule, IKModule, limit_excess, pose_loss

TDCR3_YAML = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"


def ik_module(features: str, dtype=torch.float64, **kwargs) -> tuple[IKModule, dict]:
    spec = RobotSpec.from_yaml(TDCR3_YAML)
    data = generate(spec, 64, seed=7, dtype=dtype)
    torch.manual_seed(0)
    module = IKModule(robot=spec.to_dict(), features=features, width=16, depth=2, **kwargs).to(dtype)
    module.model.fit_normalization(data["q"], data["pose"])
    return module, data


@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_decoded_features_are_those_of_the_decoded_joints(features):
    """decode_features(z) = encoder(decode(z)) (Clarke: without the round trip; raw: the projection)."""
    module, data = ik_module(features)
    model = module.model
    z = model.forward_normalized(data["pose"])
    expected = model.encoder(model.decode(z))
    scale = expected.abs().max().item()
    assert torch.allclose(model.decode_features(z), expected, atol=1e3 * torch.finfo(z.dtype).eps * scale, rtol=0)


@pytest.mark.parametrize("output_scale", ["std", "task"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_pose_loss_vanishes_at_the_true_joints(features, dtype, output_scale):
    """A network output equal to the standardised true target has zero pose loss (to round-off of the
    standardisation and the FK; the loss is a squared relative error, so ~ (1e3·eps)²)."""
    module, data = ik_module(features, dtype, output_scale=output_scale)
    model = module.model
    z = model.out_norm(model.target(data["q"]))
    pred = forward_kinematics(module.spec, model.decode_features(z))
    assert torch.allclose(pred, data["pose"], atol=1e3 * torch.finfo(dtype).eps * module.spec.total_length)
    assert pose_loss(pred, data["pose"], module.spec.total_length) < (1e3 * torch.finfo(dtype).eps) ** 2
    shifted = forward_kinematics(module.spec, model.decode_features(z + 0.1))
    assert pose_loss(shifted, data["pose"], module.spec.total_length) > 1e-6      # and it does see an error


@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_pose_loss_gradient_through_decoder_and_fk(features):
    """gradcheck (float64) of z ↦ pose loss of the analytic FK of the decoded prediction."""
    module, data = ik_module(features)
    model, pose = module.model, data["pose"][:6]
    z0 = model.forward_normalized(pose).detach().requires_grad_(True)

    def loss(z):
        pred = forward_kinematics(module.spec, model.decode_features(z))
        return pose_loss(pred, pose, module.spec.total_length, rot_weight=0.5)

    assert torch.autograd.gradcheck(loss, (z0,), eps=1e-6, atol=1e-8)


def test_training_loss_combines_feature_and_pose_terms():
    """loss = feature_weight·(feature MSE) + pose_weight·(pose loss), each term checked on its own."""
    batch = {}
    losses = {}
    for fw, pw in ((1.0, 0.0), (0.0, 1.0), (0.3, 2.0)):
        module, data = ik_module("clarke", feature_weight=fw, pose_weight=pw, rot_weight=0.5)
        batch = {"q": data["q"], "pose": data["pose"]}
        losses[fw, pw] = module.loss(batch)
    combined = 0.3 * losses[1.0, 0.0] + 2.0 * losses[0.0, 1.0]
    assert torch.allclose(losses[0.3, 2.0], combined, rtol=1e3 * torch.finfo(torch.float64).eps)
    assert losses[0.0, 1.0] > 0 and losses[1.0, 0.0] > 0


@pytest.mark.parametrize("kwargs,match", [({"feature_weight": 0.0, "pose_weight": 0.0}, "at least one"),
                                          ({"pose_weight": -1.0}, "pose_weight: expected a number >= 0"),
                                          ({"rot_weight": float("nan")}, "rot_weight"),
                                          ({"pose_ramp": 1.5}, "pose_ramp: expected a fraction"),
                                          ({"limit_weight": -0.1}, "limit_weight: expected a number >= 0"),
                                          ({"pose_ramp_max_epochs": 0}, "pose_ramp_max_epochs: expected"),
                                          ({"pose_ramp_max_epochs": float("nan")}, "pose_ramp_max_epochs"),
                                          ({"output_scale": "range"}, "output_scale: expected one of"),
                                          ({"limit_noise": -0.1}, "limit_noise: expected a standard deviation"),
                                          ({"limit_noise_reference_n": 0}, "limit_noise_reference_n: expected"),
                                          ({"limit_noise_reference_n": 1e3}, "limit_noise_reference_n: expected"),
                                          ({"pose_noise": -0.1}, "pose_noise: expected a standard deviation"),
                                          ({"pose_noise_weight": -1.0}, "pose_noise_weight: expected a number")])
def test_bad_loss_weights_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        IKModule(robot=str(TDCR3_YAML), **kwargs)


def test_pose_ramp_moves_from_the_feature_loss_to_the_final_weights():
    """pose_ramp = 0.5 of 100 steps: (1, 0) at step 0, halfway at step 25, final weights from step 50 on."""
    module, _ = ik_module("clarke", feature_weight=0.01, pose_weight=2.0, pose_ramp=0.5)
    assert module.loss_weights() == (0.01, 2.0)                       # outside a fit: the final weights
    module._trainer = SimpleNamespace(global_step=0, estimated_stepping_batches=100)
    module.train()
    expected = {0: (1.0, 0.0), 25: (0.505, 1.0), 50: (0.01, 2.0), 99: (0.01, 2.0)}
    for step, (wf, wp) in expected.items():
        module._trainer.global_step = step
        assert module.loss_weights() == pytest.approx((wf, wp), rel=1e-12), step


@pytest.mark.parametrize("batches_per_epoch,ramp_steps", [(4, 20), (40, 50)])
def test_pose_ramp_max_epochs_caps_the_ramp_at_so_many_epochs(batches_per_epoch, ramp_steps):
    """pose_ramp 0.5 of 100 steps, at most 5 epochs: 4 batches per epoch → the ramp ends at step 20 (halfway
    at 10); 40 batches per epoch → the cap (200 steps) is above the fraction, which rules (50 steps)."""
    module, _ = ik_module("clarke", feature_weight=0.0, pose_weight=1.0, pose_ramp=0.5, pose_ramp_max_epochs=5)
    module._trainer = SimpleNamespace(global_step=0, estimated_stepping_batches=100,
                                      num_training_batches=batches_per_epoch)
    module.train()
    for step, (wf, wp) in {0: (1.0, 0.0), ramp_steps // 2: (0.5, 0.5), ramp_steps: (0.0, 1.0),
                           99: (0.0, 1.0)}.items():
        module._trainer.global_step = step
        assert module.loss_weights() == pytest.approx((wf, wp), rel=1e-12), step


def test_ik_errors_count_the_predictions_outside_the_joint_limits():
    """IKModule.errors flags a prediction whose decoded features exceed the limits (limit_excess > 1e-6):
    none for a fresh network's near-mean outputs; some, exactly those, once the output layer is scaled up;
    summarize reports their share in percent."""
    from dacr_learn.metrics import summarize

    module, data = ik_module("clarke")
    batch = {"q": data["q"], "pose": data["pose"]}
    assert module.errors(batch)["out_of_limits"].sum() == 0
    with torch.no_grad():
        module.model.net[-1].weight.mul_(20.0)
    flags = module.errors(batch)["out_of_limits"]
    excess = limit_excess(module.spec, module.model.encoder(module.model(data["pose"])))
    assert 0 < flags.sum() < len(flags)
    assert torch.equal(flags.bool(), excess > 1e-6)
    share = summarize({"out_of_limits": flags}, module.spec.total_length)["out_of_limits_pct"]
    assert share == pytest.approx(100 * flags.mean().item())


def test_limit_noise_adds_the_penalty_at_noisy_inputs():
    """limit_noise σ: loss = loss(σ = 0) + limit_weight · mean limit_excess of the prediction at the standardised
    input plus σ·N(0, 1) (the same draw reproduced here), with predictions pushed out of the limits."""
    losses = {}
    for noise in (0.0, 0.5):
        module, data = ik_module("clarke", feature_weight=0.0, pose_weight=1.0, limit_weight=2.0, limit_noise=noise)
        model = module.model
        with torch.no_grad():
            model.net[-1].weight.mul_(20.0)
        torch.manual_seed(5)
        losses[noise] = module.loss({"q": data["q"], "pose": data["pose"]})
    x = model.in_norm(pose_to_vector(data["pose"], module.spec.total_length))
    torch.manual_seed(5)
    noisy = model.decode_features(model.net(x + 0.5 * torch.randn_like(x)))
    extra = 2.0 * limit_excess(module.spec, noisy).mean()
    assert extra > 0.01
    assert torch.allclose(losses[0.5], losses[0.0] + extra, rtol=1e3 * torch.finfo(torch.float64).eps)


@pytest.mark.parametrize("reference,n_train,expected", [(None, 100000, 2.0), (1000, 1000, 2.0), (1000, 10000, 0.02),
                                                        (1000, 100000, 2e-4), (1000, 500, 8.0)])
def test_limit_noise_weight_falls_with_the_training_set_size(reference, n_train, expected):
    """limit_weight 2 at limit_noise_reference_n samples: the noisy-input penalty of a fit on n_train samples
    (setup reads the size from the datamodule) weighs 2 · (reference / n_train)²; 2 at every size without a
    reference."""
    module, data = ik_module("clarke", limit_weight=2.0, limit_noise=0.5, limit_noise_reference_n=reference)
    train = {"q": data["q"][:1].expand(n_train, -1), "pose": data["pose"][:1].expand(n_train, 4, 4)}
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(splits={"train": train}))
    module.setup("fit")
    assert module.n_train == n_train
    assert module.noise_weight() == pytest.approx(expected, rel=1e-12)


def test_limit_noise_reference_needs_the_training_set_size():
    module, _ = ik_module("clarke", limit_weight=1.0, limit_noise=0.3, limit_noise_reference_n=1000)
    with pytest.raises(ValueError, match="limit_noise_reference_n: needs the training set size"):
        module.noise_weight()


def test_input_pose_inverts_the_standardised_input_and_maps_any_vector_to_a_pose():
    """IKModel.input_pose: the poses back from their standardised inputs (to round-off); a perturbed input gives a
    rotation matrix (orthonormal, det 1) and the perturbed position."""
    module, data = ik_module("raw")
    model = module.model
    x = model.normalized_input(data["pose"])
    assert torch.allclose(model.input_pose(x), data["pose"], atol=1e3 * torch.finfo(x.dtype).eps, rtol=0)
    noisy = model.input_pose(x + 0.5 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3),
                                                   dtype=x.dtype))
    rot = noisy[..., :3, :3]
    assert torch.allclose(rot @ rot.mT, torch.eye(3, dtype=x.dtype).expand_as(rot), atol=1e-12)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(len(rot), dtype=x.dtype), atol=1e-12)
    assert (noisy[..., :3, 3] - data["pose"][..., :3, 3]).abs().max() > 1e-4
    assert torch.equal(noisy[..., 3, :], data["pose"][..., 3, :])


@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_pose_noise_adds_the_pose_loss_at_perturbed_training_poses(features):
    """pose_noise σ, pose_noise_weight w, pose weight 2 at (reference / n_train)² = 1/4: loss = loss(σ = 0) +
    2 · w / 4 · pose loss of the prediction at the training inputs plus σ·N(0, 1) (the same draw reproduced
    here), against the poses those perturbed inputs encode (not the training poses)."""
    losses = {}
    for noise in (0.0, 0.4):
        module, data = ik_module(features, feature_weight=0.0, pose_weight=2.0, rot_weight=0.5, pose_noise=noise,
                                 pose_noise_weight=3.0, limit_noise_reference_n=32)
        module.n_train = 64
        torch.manual_seed(5)
        losses[noise] = module.loss({"q": data["q"], "pose": data["pose"]})
    model = module.model
    x = model.normalized_input(data["pose"])
    torch.manual_seed(5)
    target = model.input_pose(x + 0.4 * torch.randn_like(x))
    pred = forward_kinematics(module.spec, model.decode_features(model.net(model.normalized_input(target))))
    extra = 2.0 * 3.0 / 4 * pose_loss(pred, target, module.spec.total_length, 0.5)
    assert extra > 1e-3
    assert torch.allclose(losses[0.4], losses[0.0] + extra, rtol=1e3 * torch.finfo(torch.float64).eps)
    against_training_poses = 2.0 * 3.0 / 4 * pose_loss(pred, data["pose"], module.spec.total_length, 0.5)
    assert not torch.allclose(losses[0.4], losses[0.0] + against_training_poses, rtol=1e-3)


def test_limit_excess_is_zero_inside_the_limits_and_the_relative_overshoot_squared_outside():
    """Sampled features (inside the limits, the bend reaching them) → 0; segment 1 bent to 1.5 × its limit
    → 0.5²; segment 3 half a half-range above its longest → 0.5²; both → the sum."""
    spec = RobotSpec.from_yaml(TDCR3_YAML)
    features = generate(spec, 256, seed=3, dtype=torch.float64)["features"]
    assert limit_excess(spec, features).abs().max() == 0
    seg1, seg3 = spec.segments[0], spec.segments[2]
    f = features[:4].clone()
    f[0, 0, :2] = torch.tensor([0.6, 0.8], dtype=f.dtype) * 1.5 * seg1.radius * seg1.bend
    lo, hi = seg3.length_range
    f[1, 2, 2] = hi + (hi - lo) / 4
    f[2, 2, 2] = lo - (hi - lo) / 4
    f[3] = torch.stack([f[0, 0], f[3, 1], f[1, 2]])
    expected = torch.tensor([0.25, 0.25, 0.25, 0.5], dtype=f.dtype)
    assert torch.allclose(limit_excess(spec, f), expected, atol=1e3 * torch.finfo(f.dtype).eps)


def test_limit_weight_adds_the_mean_limit_excess_of_the_decoded_features():
    """loss(limit_weight = w) = loss(0) + w · mean limit_excess(decode_features(z)), with predictions
    pushed out of the limits (a fresh network scaled up) so that the term is not zero; gradcheck."""
    losses, excess = {}, None
    for w in (0.0, 2.5):
        module, data = ik_module("clarke", feature_weight=0.0, pose_weight=1.0, limit_weight=w)
        with torch.no_grad():
            module.model.net[-1].weight.mul_(20.0)
        batch = {"q": data["q"], "pose": data["pose"]}
        losses[w] = module.loss(batch)
        excess = limit_excess(module.spec, module.model.decode_features(module.model.forward_normalized(data["pose"])))
    assert excess.mean() > 0.01
    assert torch.allclose(losses[2.5], losses[0.0] + 2.5 * excess.mean(), rtol=1e3 * torch.finfo(torch.float64).eps)
    spec, features = module.spec, module.model.decode_features(module.model.forward_normalized(data["pose"][:6]))
    assert torch.autograd.gradcheck(lambda f: limit_excess(spec, f).sum(), (features.detach().requires_grad_(True),))


@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_task_output_scale_makes_every_output_move_the_pose_alike(features):
    """output_scale="task": the median over the fitted samples of ‖∂v/∂z_i‖ (v = pose_to_vector of the FK of
    the decoded output) is the same for every output i, and the scales keep the geometric mean of the
    std-based ones. With "std" the Clarke outputs differ by more than 10x (β barely moves the tip)."""
    gains = {}
    for scale in ("std", "task"):
        module, data = ik_module(features, output_scale=scale)
        model = module.model
        z = model.out_norm(model.target(data["q"])).requires_grad_(True)
        v = pose_to_vector(forward_kinematics(module.spec, model.decode_features(z)), module.spec.total_length)
        jac = torch.stack([torch.autograd.grad(v[:, i].sum(), z, retain_graph=True)[0] for i in range(9)])
        gains[scale] = jac.norm(dim=0).median(dim=0).values
        if scale == "std":
            std = model.out_norm.std.clone()
        else:
            ratio = model.out_norm.std / std
            assert torch.log(ratio).mean().abs() < 1e-6
    task = gains["task"]
    assert torch.allclose(task, task.mean().expand_as(task), rtol=1e-6)
    if features == "clarke":
        assert gains["std"].max() > 10 * gains["std"].min()


@pytest.mark.parametrize("total", [4, 5, 19, 39, 40, 1000])
def test_one_cycle_schedule_runs_short_and_long(total):
    from dacr_learn.training import one_cycle

    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=0.1)
    sched = one_cycle(opt, 0.1, total)
    lrs = []
    for _ in range(total):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert all(math.isfinite(v) and v > 0 for v in lrs)
    assert max(lrs) == pytest.approx(0.1, rel=1e-6) and lrs[-1] < 0.01 * max(lrs)
    with pytest.raises(ValueError, match="at least 4 training steps"):
        one_cycle(opt, 0.1, 3)


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
