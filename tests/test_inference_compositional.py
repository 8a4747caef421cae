"""dacr_learn.inference_compositional: the folded compositional FK equals the model in float64."""
from __future__ import annotations

import pytest
import torch
from conftest import roundoff_tol, spec_by_name

from dacr_learn.compositional import CompositionalFK
from dacr_learn.data import generate
from dacr_learn.inference_compositional import InferenceCompositionalFK

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64


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
