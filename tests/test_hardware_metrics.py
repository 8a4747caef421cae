"""dacr_learn.hardware.metrics: the offset-removed RMSE and the tip metrics, hand-computed."""
from __future__ import annotations

import pytest
import torch

from dacr_learn.hardware.metrics import offset_removed_rmse, tip_metrics

pytestmark = pytest.mark.usefixtures("one_thread")


def test_offset_removed_rmse_hand_computed():
    meas = torch.zeros(2, 3, dtype=torch.float64)
    pred = torch.tensor([[1.0, 0, 0], [3.0, 0, 0]], dtype=torch.float64)   # mean offset (2,0,0), residuals ±1
    assert float(offset_removed_rmse(pred, meas)) == pytest.approx(1.0)
    assert float(offset_removed_rmse(meas + torch.tensor([5.0, -2, 7]), meas)) == pytest.approx(0.0, abs=1e-12)
    pred = torch.tensor([[3e-3, 4e-3, 0], [0, 0, 0]], dtype=torch.float64)  # errors 5 mm and 0 mm
    m = tip_metrics(pred, meas)
    assert m["rmse_mm"] == pytest.approx(2.5) and m["mean_mm"] == pytest.approx(2.5)
    assert m["offset_mm"] == pytest.approx(2.5) and m["p95_mm"] == pytest.approx(0.95 * 5.0)
    with pytest.raises(ValueError, match="equal shapes"):
        offset_removed_rmse(pred, meas[:1])
