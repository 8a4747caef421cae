"""dacr_learn.deploy.inference: the folded FK / IK / Jacobian modules (what dacr_learn.export exports) equal the models
in float64 for every robot and feature mode, and the Jacobian module equals autograd of the FK."""
from __future__ import annotations

import pytest
import torch
from conftest import ROOT, autograd_jacobians, max_diff, spec_by_name

from dacr_learn.data import generate
from dacr_learn.deploy.inference import InferenceFK, InferenceIK, InferenceJacobian
from dacr_learn.models import FKModel, IKModel
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


ROBOTS = [*(p.stem for p in sorted((ROOT / "configs" / "robots").glob("*.yaml"))), "twisting"]


def _fk_model(spec: RobotSpec, features: str, rotation: str = "6d", activation: str = "silu") -> FKModel:
    torch.manual_seed(1)
    model = FKModel(spec, features, width=16, depth=2, activation=activation, rotation=rotation)
    model.fit_normalization(generate(spec, 256, seed=1)["q"])
    return model.double().eval()


@pytest.mark.parametrize("robot", ROBOTS)
@pytest.mark.parametrize("features", ["clarke", "raw"])
def test_folded_fk_and_ik_equal_models_float64(robot, features):
    spec = spec_by_name(robot)
    data = generate(spec, 32, seed=2, dtype=torch.float64)
    model = _fk_model(spec, features)
    with torch.no_grad():
        assert max_diff(InferenceFK(model, torch.float64)(data["q"]), model(data["q"])) <= 1e-12
        ik = IKModel(spec, features, width=16, depth=2).double()
        ik.fit_normalization(data["q"], data["pose"])
        assert max_diff(InferenceIK(ik, torch.float64)(data["pose"]), ik(data["pose"])) <= 1e-12


@pytest.mark.parametrize("robot", ["type1", "type3", "tdcr_3seg_coupled", "asymmetric", "twisting"])
@pytest.mark.parametrize("features,rotation,activation", [("clarke", "6d", "silu"), ("raw", "6d", "tanh"),
                                                          ("clarke", "quaternion", "gelu"),
                                                          ("raw", "quaternion", "relu")])
def test_jacobian_module_equals_jacrev(robot, features, rotation, activation):
    spec = spec_by_name(robot)
    model = _fk_model(spec, features, rotation, activation)
    q = generate(spec, 3, seed=4, dtype=torch.float64)["q"]
    pose, jac_f, jac_q = InferenceJacobian(model, torch.float64)(q)
    for i in range(len(q)):
        ref_f, ref_q = autograd_jacobians(model, spec, q[i])
        scale = max(1.0, ref_q.abs().max().item())
        assert max_diff(jac_q[i], ref_q) <= 1e-9 * scale
        assert max_diff(jac_f[i], ref_f) <= 1e-9 * max(1.0, ref_f.abs().max().item())
    assert max_diff(pose, model(q)) <= 1e-12
