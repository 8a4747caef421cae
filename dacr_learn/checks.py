"""Input validation shared by the public tensor functions: clear ValueErrors, never silent broadcasting."""
from __future__ import annotations

import torch
from torch import Tensor


def check_tensor(x: Tensor, name: str, trailing: tuple[int, ...], finite: bool = True) -> None:
    """Raise ValueError unless ``x`` is a floating tensor of shape (..., *trailing) with finite values.

    Skipped while tracing for torch.export / torch.compile (the checks are data dependent).
    """
    if torch.compiler.is_compiling():
        return
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape (..., {', '.join(map(str, trailing))}), "
                         f"got {type(x).__name__}")
    k, expected = len(trailing), f"(..., {', '.join(map(str, trailing))})"
    if x.dim() < k or tuple(x.shape[x.dim() - k:]) != tuple(trailing):
        raise ValueError(f"{name}: expected shape {expected}, got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    # A NaN/inf anywhere makes the sum non-finite; the sum is one cheap reduction, the exact
    # elementwise test only runs when it fails (or a huge finite sum overflowed).
    if finite and not bool(torch.isfinite(x.sum())) and not bool(torch.isfinite(x).all()):
        bad = (~torch.isfinite(x)).sum().item()
        raise ValueError(f"{name}: expected finite values of shape {expected}, got {bad} NaN/inf entries "
                         f"in a tensor of shape {tuple(x.shape)}")
