"""Models: front-ends, FK/IK heads, constraint satisfaction, batching."""

import pytest
import torch

from dacr_learn.data import generate
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.models import FEATURE_MODES, FeatureFrontEnd, FKModel, IKModel, Standardizer, actuated_selection
from dacr_learn.robot import RobotSpec

ROBOTS = ["default", "type1", "type3", "tdcr_3seg_coupled", "asymmetric"]


def spec_of(name):
    return RobotSpec.from_yaml(f"configs/robots/{name}.yaml")


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("mode", FEATURE_MODES)
def test_front_end_and_fk_batched_equal_single_in_float32(name, mode):
    spec = spec_of(name)
    d = generate(spec, 64, 0)
    torch.manual_seed(0)
    model = FKModel(spec, mode, width=32, depth=2)
    model.fit_normalization(d["q"])
    batched_front, batched_pose = model.front(d["q"]), model(d["q"])
    single_front = torch.stack([model.front(q) for q in d["q"]])
    single_pose = torch.stack([model(q) for q in d["q"]])
    assert batched_front.dtype == torch.float32
    # batched GEMM and per-sample GEMV sum in different orders: equal up to float32 rounding
    # (values here are O(1); 1e-5 is ~100 ulp, far below any modelling error)
    assert torch.allclose(batched_front, single_front, atol=1e-5, rtol=0)
    assert torch.allclose(batched_pose, single_pose, atol=1e-5, rtol=0)
    assert model(d["q"].reshape(8, 8, -1)).shape == (8, 8, 4, 4)


def test_clarke_front_end_selects_exactly_the_actuated_columns():
    spec = spec_of("type3")                       # ρ_re, ρ_im, β, α all actuated
    d = generate(spec, 10, 0, dtype=torch.float64)
    front = FeatureFrontEnd(spec, "clarke").double()
    assert torch.allclose(front.raw_features(d["q"]), d["features"][:, 0, :], atol=1e-12)
    assert actuated_selection(spec_of("default")).shape == (2, 4)
    assert actuated_selection(spec_of("tdcr_3seg_coupled")).shape == (9, 12)
    with pytest.raises(ValueError, match="features"):
        FeatureFrontEnd(spec, "fourier")


def test_standardised_clarke_features_have_zero_mean_unit_std_on_training_data():
    spec = spec_of("type1")
    d = generate(spec, 5000, 0)
    front = FeatureFrontEnd(spec, "clarke")
    front.fit(d["q"])
    z = front(d["q"])
    assert torch.allclose(z.mean(0), torch.zeros(3), atol=1e-4)
    assert torch.allclose(z.std(0), torch.ones(3), atol=1e-3)


@pytest.mark.parametrize("name", ROBOTS)
def test_clarke_ik_outputs_satisfy_the_displacement_constraint(name):
    spec = spec_of(name)
    d = generate(spec, 200, 0, dtype=torch.float64)
    ik = IKModel(spec, "clarke", width=32, depth=2).double()
    ik.fit_normalization(d["q"], d["pose"])
    with torch.no_grad():
        q = ik(d["pose"] + 0.01 * torch.randn_like(d["pose"]))         # untrained, off-manifold inputs
    residual = q - ClarkeDecoder(spec).double()(ClarkeEncoder(spec).double()(q))
    assert residual.abs().max() < 1e-12
    raw = IKModel(spec, "raw", width=32, depth=2).double()
    raw.fit_normalization(d["q"], d["pose"])
    with torch.no_grad():
        q_raw = raw(d["pose"])
    raw_residual = q_raw - ClarkeDecoder(spec).double()(ClarkeEncoder(spec).double()(q_raw))
    if spec.num_joints > spec.num_actuated_features:                     # redundant joints: a constraint exists
        assert raw_residual.abs().max() > 1e-6                           # the baseline has no such guarantee


def test_quaternion_head_and_bad_options():
    spec = spec_of("default")
    pose = FKModel(spec, rotation="quaternion", width=16, depth=1)(torch.full((3, 4), 0.1))
    r = pose[:, :3, :3]
    assert torch.allclose(r @ r.mT, torch.eye(3).expand(3, 3, 3), atol=1e-5)
    assert torch.equal(pose[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(3, 4))
    with pytest.raises(ValueError, match="rotation"):
        FKModel(spec, rotation="euler")
    with pytest.raises(ValueError, match="activation"):
        FKModel(spec, activation="swish")
    with pytest.raises(ValueError, match="joint vector"):
        FKModel(spec)(torch.zeros(3, 5))


def test_standardizer_fits_in_float64_unless_asked_and_stores_in_its_buffers_dtype():
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(5000, 3, generator=g) * torch.tensor([1e-3, 1.0, 30.0]) + torch.tensor([0.02, -3.0, 1e3])).float()
    exact, single = Standardizer(3), Standardizer(3)
    exact.fit(x)
    single.fit(x, dtype=torch.float32)                # the hardware baselines' statistics (float32 sums)
    assert exact.mean.dtype == single.mean.dtype == torch.float32
    assert torch.equal(exact.mean, x.double().mean(0).float()) and torch.equal(exact.std, x.double().std(0).float())
    assert torch.equal(single.mean, x.mean(0)) and torch.equal(single.std, x.std(0))
    assert torch.allclose(exact.inverse(exact(x)), x, rtol=1e-6, atol=1e-4)
