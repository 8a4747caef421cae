"""Tip-error metrics for hardware benchmarks (inputs in metres, reports in millimetres).

The lab's metric is the *offset-removed RMSE*: with errors e_k = pred_k − meas_k (n, 3) and their mean ē,
RMSE = sqrt(mean_k ‖e_k − ē‖²): it forgives a constant offset (marker placement, base registration). The mean
and 95th percentile of the plain Euclidean errors ‖e_k‖ are reported alongside.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import check_tensor


def offset_removed_errors(pred: Tensor, meas: Tensor) -> Tensor:
    """‖e_k − ē‖ per row of e = pred − meas (ē: the mean over all n rows), shapes (n, 3) → (n,) (same unit, pred's
    dtype): the terms of the offset-removed RMSE."""
    check_tensor(pred, "pred", (3,))
    check_tensor(meas, "meas", (3,))
    if pred.shape != meas.shape or pred.dim() != 2 or pred.shape[0] == 0:
        raise ValueError(f"pred/meas: expected equal shapes (n, 3) with n > 0, got {tuple(pred.shape)} "
                         f"and {tuple(meas.shape)}")
    e = pred - meas
    return (e - e.mean(0)).norm(dim=-1)


def offset_removed_rmse(pred: Tensor, meas: Tensor) -> Tensor:
    """sqrt(mean ‖e − ē‖²) over rows of e = pred − meas, shapes (n, 3) → scalar (same unit)."""
    return offset_removed_errors(pred, meas).pow(2).mean().sqrt()


def tip_metrics(pred: Tensor, meas: Tensor) -> dict[str, float]:
    """{rmse_mm (offset removed), mean_mm, p95_mm (Euclidean, offset kept), offset_mm (‖ē‖)}."""
    rmse = offset_removed_rmse(pred, meas)
    e = (pred - meas).double()
    dist = e.norm(dim=-1)
    return {"rmse_mm": float(rmse) * 1e3, "mean_mm": float(dist.mean()) * 1e3,
            "p95_mm": float(torch.quantile(dist, 0.95)) * 1e3, "offset_mm": float(e.mean(0).norm()) * 1e3}
