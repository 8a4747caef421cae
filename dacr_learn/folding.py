"""Folding an MLP for inference: forward-mode tangent rows, affine maps found by probing, stacked ensembles.

The one home of what every folded inference module (:mod:`.deploy.inference`,
:mod:`.deploy.inference_compositional`, :mod:`.hardware.deploy`) does to a network besides running it
(:func:`tangent_rows`, :func:`affine_probe`, :func:`stacked_linear`). Pure torch; everything here is traced by
torch.export like the modules that call it.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .checks import F64
from .models import ACTIVATIONS

__all__ = ["activation_and_derivative", "activation_name", "affine_probe", "linear_layers", "stacked_linear",
           "tangent_rows"]

_ACTIVATIONS = {name: cls() for name, cls in ACTIVATIONS.items()}   # one (stateless) module of each


def linear_layers(net: nn.Sequential) -> list[nn.Linear]:
    """The nn.Linear layers of ``net``, in order."""
    return [m for m in net if isinstance(m, nn.Linear)]


def activation_name(nets: nn.Sequential | Sequence[nn.Sequential]) -> str:
    """The name (a key of models.ACTIVATIONS) of the one activation every net of ``nets`` uses; a ValueError
    names the activations found otherwise."""
    nets = [nets] if isinstance(nets, nn.Sequential) else list(nets)
    kinds = {type(m) for net in nets for m in net if not isinstance(m, nn.Linear)}
    names = [k for k, cls in ACTIVATIONS.items() if {cls} == kinds]
    if len(names) != 1:
        raise ValueError(f"net: expected one activation of {sorted(ACTIVATIONS)}, got "
                         f"{sorted(k.__name__ for k in kinds)}")
    return names[0]


def activation_and_derivative(name: str, a: Tensor) -> tuple[Tensor, Tensor]:
    """(σ(a), σ'(a)) for the activations of models.ACTIVATIONS (GELU: exact erf form)."""
    if name == "silu":
        sg = torch.sigmoid(a)
        return a * sg, sg * (1 + a * (1 - sg))
    if name == "relu":
        return F.relu(a), (a > 0).to(a.dtype)
    if name == "gelu":
        cdf = 0.5 * (1 + torch.erf(a * (1 / math.sqrt(2))))
        return a * cdf, cdf + a * torch.exp(-0.5 * a * a) * (1 / math.sqrt(2 * math.pi))
    s = torch.tanh(a)
    return s, 1 - s * s


def tangent_rows(rows: Tensor, layers: Sequence[tuple[Tensor, Tensor]], activation: str) -> Tensor:
    """Forward mode through an MLP's layers after the first pre-activation, as stacked rows.

    rows (..., 1 + T, W): the first layer's pre-activation (row 0) and its T tangents (rows 1 … T). Each of
    ``layers`` (weight, bias) applies σ to the value row and σ'(value)·tangent to the others, then the
    weight to all rows and the bias to the value row only. Weights (in, out) with biases (out,), or K
    members' weights (K, in, out) with biases (K, 1, out) for rows (K, R, 1 + T, W) (one batched product).
    Returns (..., 1 + T, out): the network output and its T tangents. With no tangent rows (T = 0) this is
    the plain forward pass.
    """
    n = rows.shape[-2]
    value_row = (torch.arange(n, device=rows.device) == 0).to(rows.dtype).unsqueeze(-1)   # (1 + T, 1)
    a = rows
    for weight, bias in layers:
        if n == 1:                                             # no tangents: the plain forward pass
            a = _ACTIVATIONS[activation](a)
        else:
            s, ds = activation_and_derivative(activation, a[..., :1, :])
            a = torch.cat([s, a[..., 1:, :] * ds], dim=-2)
        if weight.dim() == 3:                                  # K members (K, R, 1 + T, in): one batched product
            flat = a.reshape(a.shape[0], -1, a.shape[-1])
            if n == 1:
                a = torch.baddbmm(bias, flat, weight).view(*a.shape[:-1], -1)
            else:
                a = torch.bmm(flat, weight).view(*a.shape[:-1], -1) + bias.unsqueeze(1) * value_row
        else:
            a = F.linear(a, weight.mT, bias) if n == 1 else a @ weight + bias * value_row
    return a


def affine_probe(fn: Callable[[Tensor], Tensor], width: int, dtype: torch.dtype = F64) -> tuple[Tensor, Tensor]:
    """(M (width, out), c (out,)) with fn(x) = x·M + c for an affine ``fn`` of x (P, width) → (P, ...): its
    values at 0 and at the ``width`` unit vectors (exact for an affine map; flattened after the batch dim)."""
    basis = torch.cat([torch.zeros(1, width, dtype=dtype), torch.eye(width, dtype=dtype)])
    out = fn(basis).flatten(1)
    return (out[1:] - out[:1]).contiguous(), out[0].clone()


def stacked_linear(layers: Sequence[nn.Linear], scale: Tensor | float = 1.0) -> tuple[Tensor, Tensor]:
    """One linear layer of K members side by side, float64: weights (K, in, out) and biases (K, 1, out),
    both times ``scale`` (broadcast against (K, 1, out), e.g. a per-member output scale)."""
    weight = torch.stack([l.weight.detach() for l in layers]).to(F64).mT * scale
    bias = torch.stack([l.bias.detach() for l in layers]).to(F64).unsqueeze(1) * scale
    return weight, bias
