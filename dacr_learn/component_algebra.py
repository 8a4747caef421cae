"""Zero-aware algebra of 3-vectors and 3 × 3 matrices in component form, the arithmetic of :mod:`.lie`'s kernel.

A vector is a tuple of three tensors (...), a rotation a tuple of nine (row-major); a component may be None, an
exact zero that costs no operation (a constant-curvature twist has three). Components are separate contiguous
tensors rather than a (..., 3) last dim: elementwise products of whole tensors beat small batched matmuls, and
the zeros can be skipped. Pure torch.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["Rot3", "Vec3", "add", "components", "cross", "dense", "dot", "matmul", "matvec", "neg", "prod", "scaled"]

Vec3 = tuple  # three components; a component may be None, an exact zero that costs no operation
Rot3 = tuple  # nine components, row-major


NO_FACTOR = object()


def prod(a, b, c=NO_FACTOR):
    """a·b (·c), None (exact zero) if any factor is None."""
    if a is None or b is None or c is None:
        return None
    return a * b if c is NO_FACTOR else a * b * c


def add(*terms):
    """The sum of the terms that are not None (None if all are)."""
    out = None
    for t in terms:
        if t is not None:
            out = t if out is None else out + t
    return out


def neg(x):
    return None if x is None else -x


def dot(a: Vec3, b: Vec3):
    return add(*(prod(x, y) for x, y in zip(a, b, strict=True)))


def cross(a: Vec3, b: Vec3) -> Vec3:
    return tuple(add(prod(a[i], b[j]), neg(prod(a[j], b[i]))) for i, j in ((1, 2), (2, 0), (0, 1)))


def matvec(r: Rot3, x: Vec3) -> Vec3:
    return tuple(dot(r[3 * i:3 * i + 3], x) for i in range(3))


def matmul(a: Rot3, b: Rot3) -> Rot3:
    return tuple(dot(a[3 * i:3 * i + 3], b[j::3]) for i in range(3) for j in range(3))


def scaled(c, x: Vec3) -> Vec3:
    return tuple(prod(c, xi) for xi in x)


def components(x: Tensor) -> tuple[Tensor, ...]:
    """The last dim of x (..., k) as k contiguous tensors (...)."""
    return x.movedim(-1, 0).contiguous().unbind(0)


def dense(x: tuple, like: Tensor) -> tuple[Tensor, ...]:
    """Components with None (exact zeros) replaced by zero tensors of ``like``'s shape."""
    return tuple(torch.zeros_like(like) if c is None else c if c.shape == like.shape else c.expand_as(like) for c in x)
