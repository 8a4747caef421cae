"""Admissible sets of IK variables: boxes and disks, batched (float64).

An IK variable vector x (..., D) is admissible when every box coordinate lies in [lower, upper] and every
disk pair (x_i, x_j) has ‖(x_i, x_j)‖ ≤ r. In Clarke space a segment's bending limit is a disk
(‖ρ‖ = d·φ ≤ d·bend), its length and twist ranges are boxes; servo commands of a hardware model are a box.
:class:`Limits` projects onto the set (the nearest admissible point: clamp, radial shrink), tells which
constraints are active for a step, samples uniformly inside and measures violations. Build one with the named
constructors :meth:`Limits.boxes`, :meth:`Limits.disk` and :meth:`Limits.concatenate`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from .checks import F64


@dataclass(frozen=True)
class Limits:
    """Box and disk constraints on D variables.

    lower, upper (D,): box bounds [variable units], ±inf where a coordinate has none (disk coordinates);
    disks (k, 2) long: index pairs constrained to ‖(x_i, x_j)‖ ≤ radius (k,); scale (D,): a typical
    range of each variable (the solver's unit: ρ by its disk radius, β and α by their half-ranges, a
    servo by its half-range). ``names`` (D,) label the variables in messages. Built by :meth:`boxes`,
    :meth:`disk` and :meth:`concatenate`.
    """

    lower: Tensor
    upper: Tensor
    disks: Tensor
    radius: Tensor
    scale: Tensor
    names: tuple[str, ...]

    def __post_init__(self):
        d = self.lower.shape[0]
        if self.upper.shape != (d,) or self.scale.shape != (d,) or len(self.names) != d:
            raise ValueError(f"limits: lower, upper, scale and names must have one entry per variable ({d})")
        if self.disks.shape != (self.radius.shape[0], 2):
            raise ValueError(f"limits: disks must be (k, 2) index pairs with one radius each, got "
                             f"{tuple(self.disks.shape)} and {tuple(self.radius.shape)}")
        if not bool((self.lower < self.upper).all()) or not bool((self.radius > 0).all()):
            raise ValueError("limits: every box needs lower < upper and every disk a radius > 0")
        if not bool((self.scale > 0).all()):
            raise ValueError("limits: every scale must be > 0")

    @classmethod
    def boxes(cls, lower, upper, names: tuple[str, ...], scale=None) -> Limits:
        """lower ≤ x ≤ upper on D variables (sequences or (D,) tensors, float64) [variable units]; ``scale``
        (D,) defaults to the half-ranges (upper − lower) / 2."""
        lower, upper = torch.as_tensor(lower, dtype=F64), torch.as_tensor(upper, dtype=F64)
        scale = (upper - lower) / 2 if scale is None else torch.as_tensor(scale, dtype=F64)
        return cls(lower, upper, torch.zeros(0, 2, dtype=torch.long), torch.zeros(0, dtype=F64), scale, tuple(names))

    @classmethod
    def disk(cls, radius: float, names: tuple[str, str]) -> Limits:
        """‖(x_0, x_1)‖ ≤ radius on two variables (no box bounds; the scale of both is the radius)."""
        inf = torch.full((2,), torch.inf, dtype=F64)
        return cls(-inf, inf, torch.tensor([[0, 1]]), torch.tensor([float(radius)], dtype=F64),
                   torch.full((2,), float(radius), dtype=F64), tuple(names))

    @classmethod
    def concatenate(cls, *parts: Limits, names: tuple[str, ...] | None = None) -> Limits:
        """The limits of the parts' variables one after another (disk indices shifted); ``names`` replaces the
        joined names."""
        offsets = [0]
        for p in parts[:-1]:
            offsets.append(offsets[-1] + p.num_variables)
        cat = lambda field: torch.cat([getattr(p, field).to(F64) for p in parts])  # noqa: E731
        disks = torch.cat([p.disks + o for p, o in zip(parts, offsets, strict=True)])
        names = tuple(names) if names is not None else sum((p.names for p in parts), ())
        return cls(cat("lower"), cat("upper"), disks, cat("radius"), cat("scale"), names)

    @property
    def num_variables(self) -> int:
        return self.lower.shape[0]

    def to(self, dtype: torch.dtype) -> Limits:
        return dataclasses.replace(self, lower=self.lower.to(dtype), upper=self.upper.to(dtype),
                                   radius=self.radius.to(dtype), scale=self.scale.to(dtype))

    def project(self, x: Tensor) -> Tensor:
        """The nearest admissible point (..., D): box coordinates clamped, disk pairs shrunk radially."""
        x = torch.clamp(x, self.lower, self.upper)                                        # a new tensor
        if self.disks.numel():
            pair = x[..., self.disks]                                                    # (..., k, 2)
            norm = torch.linalg.vector_norm(pair, dim=-1, keepdim=True)
            shrink = torch.clamp(self.radius.unsqueeze(-1) / norm.clamp_min(torch.finfo(x.dtype).tiny), max=1.0)
            x[..., self.disks] = pair * shrink
        return x

    def violation(self, x: Tensor) -> Tensor:
        """(...) the largest violation of any limit, relative to the variable's scale (0 inside)."""
        box = torch.maximum(self.lower - x, x - self.upper) / self.scale
        worst = box.clamp_min(0).amax(-1)
        if self.disks.numel():
            norm = torch.linalg.vector_norm(x[..., self.disks], dim=-1)
            worst = torch.maximum(worst, ((norm - self.radius) / self.radius).clamp_min(0).amax(-1))
        return worst

    def inside(self, x: Tensor, tol: float = 1e-9) -> Tensor:
        """(...) bool: within every limit up to ``tol`` of the variable's scale."""
        return self.violation(x) <= tol

    def sample(self, n: int, generator: torch.Generator, dtype: torch.dtype = F64) -> Tensor:
        """n points (n, D) uniform inside the set: boxes uniform, disks uniform by area (r = R·√u)."""
        lo, hi = self.lower.to(dtype), self.upper.to(dtype)
        u = torch.rand(n, self.num_variables, generator=generator, dtype=dtype)
        finite = torch.isfinite(lo) & torch.isfinite(hi)
        x = torch.where(finite, lo.nan_to_num(0.0) + u * (hi - lo).nan_to_num(0.0), torch.zeros_like(u))
        if self.disks.numel():
            k = self.disks.shape[0]
            w = torch.rand(n, k, 2, generator=generator, dtype=dtype)
            r = self.radius.to(dtype) * torch.sqrt(w[..., 0])
            angle = 2 * torch.pi * w[..., 1]
            x[:, self.disks] = torch.stack([r * torch.cos(angle), r * torch.sin(angle)], dim=-1)
        return x

    def blocked(self, x: Tensor, gradient: Tensor, margin: float = 1e-10) -> tuple[Tensor, Tensor | None]:
        """The limits a descent step must not cross at x: (box (..., D) bool, disk normals (..., k, 2) or None).

        A box coordinate at its bound (within ``margin`` of its scale) whose descent direction −gradient points
        outward is blocked; a disk at its rim whose descent direction points outward blocks its radial
        direction (the unit normal is returned, zero where the disk does not block).
        """
        tol = margin * self.scale
        box = ((x <= self.lower + tol) & (gradient > 0)) | ((x >= self.upper - tol) & (gradient < 0))
        if not self.disks.numel():
            return box, None
        pair = x[..., self.disks]                                                           # (..., k, 2)
        norm = torch.linalg.vector_norm(pair, dim=-1, keepdim=True)
        normal = pair / norm.clamp_min(torch.finfo(x.dtype).tiny)
        outward = (normal * gradient[..., self.disks]).sum(-1, keepdim=True) < 0             # −g·n > 0
        rim = norm >= self.radius.unsqueeze(-1) * (1 - margin)
        return box, normal * (rim & outward).to(x.dtype)

    def free_directions(self, box: Tensor, normals: Tensor | None) -> Tensor:
        """Projector P (..., D, D) onto the directions a step may take, given what :meth:`blocked` returned:
        P = diag(not blocked) − Σ n·nᵀ over the blocked disk normals (embedded in the disk's two coordinates)."""
        d = self.num_variables
        proj = torch.diag_embed((~box).to(normals.dtype if normals is not None else torch.float64))
        if normals is not None:
            n_full = torch.zeros(*box.shape[:-1], self.disks.shape[0], d, dtype=proj.dtype, device=box.device)
            n_full.scatter_(-1, self.disks.expand(*box.shape[:-1], -1, -1), normals)
            proj = proj - n_full.mT @ n_full
        return proj
