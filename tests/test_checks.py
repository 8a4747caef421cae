"""dacr_learn.checks.check_tensor: shapes, empty batches, finiteness on both summation paths, messages."""
from __future__ import annotations

import math

import pytest
import torch

from dacr_learn.checks import check_choice, check_tensor

pytestmark = pytest.mark.usefixtures("one_thread")


def test_check_tensor_nonempty_and_messages():
    check_tensor(torch.zeros(0, 3), "x", (3,))                  # empty batches are fine by default
    with pytest.raises(ValueError, match=r"^x: expected a non-empty batch, got shape \(0, 3\)$"):
        check_tensor(torch.zeros(0, 3), "x", (3,), nonempty=True)
    with pytest.raises(ValueError, match=r"^x: expected shape \(\.\.\., 3\), got a tensor of shape \(2, 2\)$"):
        check_tensor(torch.zeros(2, 2), "x", (3,))


@pytest.mark.parametrize("n", [3, 300])                       # below / above the Python-sum size (_PY_SUM_MAX)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "inf_and_minus_inf"])
def test_check_tensor_finiteness_on_both_sum_paths(n, dtype, bad):
    x = torch.ones(n, 3, dtype=dtype)
    if bad == "inf_and_minus_inf":                             # their sum is NaN, but each entry is caught
        x[0, 0], x[-1, 2] = math.inf, -math.inf
        count = 2
    else:
        x[n // 2, 1] = bad
        count = 1
    with pytest.raises(ValueError, match=rf"^q: expected finite values of shape \(\.\.\., 3\), got {count} NaN/inf"):
        check_tensor(x, "q", (3,))
    check_tensor(x, "q", (3,), finite=False)                   # the other checks still pass


@pytest.mark.parametrize("n", [3, 300])
def test_check_tensor_accepts_finite_values_whose_sum_overflows(n):
    x = torch.full((n, 3), torch.finfo(torch.float32).max, dtype=torch.float32)   # float32 sum: inf
    check_tensor(x, "q", (3,))
    check_tensor(torch.full((n, 3), 1e308, dtype=torch.float64), "q", (3,))          # float64 sum: inf


def test_check_choice_names_the_argument_and_every_choice():
    check_choice("units", "metric", ("strain", "metric"))
    with pytest.raises(ValueError, match=r"^units: expected one of \('strain', 'metric'\), got 'mm'$"):
        check_choice("units", "mm", ("strain", "metric"))
    with pytest.raises(ValueError, match=r"^activation: expected one of \['relu', 'silu'\], got 'elu'$"):
        check_choice("activation", "elu", {"silu": 1, "relu": 2})           # a dict's keys, sorted
