"""dacr_learn.deploy.inference_compositional: the folded compositional FK equals the model in float64, and its Jacobian
module equals torch.func.jacrev of the model (J_f through the Clarke decoder, J_q) in float64."""
from __future__ import annotations

import pytest
import torch
from conftest import autograd_jacobians, roundoff_tol, spec_by_name

from dacr_learn.compositional import CompositionalFK
from dacr_learn.data import generate
from dacr_learn.deploy.inference_compositional import InferenceCompositionalFK, InferenceCompositionalJacobian

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64


@pytest.mark.parametrize("robot,context,rotation", [("tdcr_3seg_coupled", "none", "twist"),
                                                    ("tdcr_3seg_coupled", "segment", "6d"),
                                                    ("type3", "distal", "twist"), ("twisting", "none", "6d"),
                                                    ("hetero_4seg_types", "distal", "twist"),
                                                    ("hetero_3seg_coupled", "none", "6d"),
                                                    ("hetero_3seg_coupled", "full", "twist")])
@pytest.mark.parametrize("units", ["strain", "metric"])
def test_folded_equals_model_float64(robot, context, rotation, units):
    spec = spec_by_name(robot)
    torch.manual_seed(2)
    model = CompositionalFK(spec, width=8, depth=2, rotation=rotation, context=context, units=units).to(F64)
    q = generate(spec, 64, seed=11, dtype=F64)["q"]
    model.fit_normalization(q)
    folded = InferenceCompositionalFK(model, F64)
    with torch.no_grad():
        assert torch.allclose(folded(q), model(q), rtol=0, atol=roundoff_tol(F64, spec.total_length, ulps=4096))


@pytest.mark.parametrize("robot,context", [("tdcr_3seg_coupled", "none"), ("tdcr_3seg_coupled", "distal"),
                                           ("type3", "segment"), ("twisting", "none"),
                                           ("hetero_4seg_types", "none"), ("hetero_5seg_coupled", "distal")])
def test_jacobian_module_equals_jacrev_float64(robot, context):
    spec = spec_by_name(robot)
    torch.manual_seed(3)
    model = CompositionalFK(spec, width=8, depth=2, rotation="twist", context=context).to(F64)
    q = generate(spec, 32, seed=5, dtype=F64)["q"]
    model.fit_normalization(q)
    module = InferenceCompositionalJacobian(model, F64)
    with torch.no_grad():
        pose, jac_f, jac_q = module(q[:6])
    torch.testing.assert_close(pose, model(q[:6]), rtol=0, atol=roundoff_tol(F64, spec.total_length, ulps=4096))
    for i in range(6):
        ref_f, ref_q = autograd_jacobians(model, spec, q[i])
        scale = float(ref_f.abs().max())
        torch.testing.assert_close(jac_f[i], ref_f, rtol=0, atol=roundoff_tol(F64, scale, ulps=4096))
        torch.testing.assert_close(jac_q[i], ref_q, rtol=0, atol=roundoff_tol(F64, float(ref_q.abs().max()), ulps=4096))


def test_jacobian_module_needs_the_twist_head():
    model = CompositionalFK(spec_by_name("tdcr_3seg_coupled"), width=8, depth=2, rotation="6d")
    with pytest.raises(ValueError, match="needs the 'twist' head"):
        InferenceCompositionalJacobian(model)
