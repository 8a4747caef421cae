"""Differentiable Clarke layers: joint vector ↔ feature tensor (docs/design.md §1, §3).

- Joint vector, shape (..., num_joints): the joint lengths of segment 1, 2, …, m [m], then the
  twist α [rad] of each twisting segment in segment order.
- Feature tensor, shape (..., m, 4): (ρ_re, ρ_im, β, α) per segment [m, m, m, rad]; columns a
  segment does not actuate hold β = l and α = 0.

Both layers hold only constant buffers (float64, cast to the input's dtype at call time), so
``.to(device)`` just works and the result follows the input's dtype and device.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .checks import check_tensor
from .clarke import joint_space_maps
from .robot import RobotSpec


class _ClarkeBase(nn.Module):
    def __init__(self, spec: RobotSpec):
        super().__init__()
        self.spec = spec
        self._cast_cache: dict = {}
        segs, m = spec.segments, spec.num_segments
        maps = joint_space_maps(spec)
        self.num_joints, self.num_segments = spec.num_joints, m
        self.num_lengths = spec.num_length_joints
        ext = [k for k, s in enumerate(segs) if s.extends]
        tw = [k for k, s in enumerate(segs) if s.twists]
        f64 = dict(dtype=torch.float64)
        self.register_buffer("displacement", maps.displacement)
        self.register_buffer("path", maps.path)
        self.register_buffer("actuated_pinv", maps.actuated_pinv)
        self.register_buffer("nominal_length", torch.tensor([s.length for s in segs], **f64))
        # Helix radius of the twist term h = sqrt((α d_i)² + β²): the joints' own radius d_i (equal
        # within a twisting segment), which may differ from the reference radius d of the Clarke
        # coordinates. Irrelevant for non-twisting segments (α = 0).
        self.register_buffer("helix_radius", torch.tensor([s.joint_radii[0] for s in segs], **f64))
        self.register_buffer("extends", torch.tensor([s.extends for s in segs]))
        self.register_buffer("twists_ext", torch.tensor([segs[k].twists for k in ext], dtype=torch.bool))
        self.register_buffer("select_ext", torch.eye(m, **f64)[:, ext])   # (m, e): per-subset → per-segment slots
        self.register_buffer("select_tw", torch.eye(m, **f64)[:, tw])

    def _c(self, name: str, like: Tensor) -> Tensor:
        """Buffer ``name`` in ``like``'s dtype and device, cast once and cached (not while tracing)."""
        buf = getattr(self, name)
        if torch.compiler.is_compiling():
            return buf.to(dtype=like.dtype, device=like.device)
        key = (name, like.dtype, like.device)
        if key not in self._cast_cache:
            self._cast_cache[key] = buf.to(dtype=like.dtype, device=like.device)
        return self._cast_cache[key]

    def _apply(self, fn, recurse=True):
        self._cast_cache = {}                     # buffers may have moved or changed dtype
        return super()._apply(fn, recurse)

    def _load_from_state_dict(self, *args, **kwargs):
        self._cast_cache = {}
        return super()._load_from_state_dict(*args, **kwargs)


class ClarkeEncoder(_ClarkeBase):
    """Joint vector (..., num_joints) → features (..., m, 4): w = B⁺(q − q₀), then β from h.

    Exact for joint vectors that satisfy the displacement constraint; the least-squares
    projection onto that constraint for noisy ones.
    """

    def forward(self, q: Tensor) -> Tensor:
        check_tensor(q, "joint vector", (self.num_joints,))
        c = lambda name: self._c(name, q)  # noqa: E731
        lengths, twist = q[..., :self.num_lengths], q[..., self.num_lengths:]
        alpha = twist @ c("select_tw").mT                                   # (..., m)
        ad2 = (alpha * c("helix_radius")) ** 2
        fixed = ~self.extends
        h_fixed = torch.where(fixed, torch.sqrt(ad2 + c("nominal_length") ** 2), torch.zeros_like(ad2))
        w = (lengths - h_fixed @ c("path").mT) @ c("actuated_pinv").mT      # (..., 2m + e)
        m = self.num_segments
        rho = w[..., :2 * m].unflatten(-1, (m, 2))
        h_ext = w[..., 2 * m:]
        ad2_ext = ad2 @ c("select_ext")
        beta_twisted = torch.sqrt(torch.clamp(h_ext**2 - ad2_ext, min=torch.finfo(q.dtype).tiny))
        beta_ext = torch.where(self.twists_ext, beta_twisted, h_ext)
        l_ext = c("nominal_length") @ c("select_ext")
        beta = c("nominal_length") + (beta_ext - l_ext) @ c("select_ext").mT
        return torch.cat([rho, beta.unsqueeze(-1), alpha.unsqueeze(-1)], dim=-1)


class ClarkeDecoder(_ClarkeBase):
    """Features (..., m, 4) → joint vector (..., num_joints): q = B_ρ·ρ + C·h, h = sqrt((αd_i)² + β²).

    Non-actuated columns are ignored (β = l for types 0/II, α = 0 for types 0/I).
    """

    def forward(self, features: Tensor) -> Tensor:
        check_tensor(features, "features", (self.num_segments, 4))
        c = lambda name: self._c(name, features)  # noqa: E731
        rho = features[..., :2].flatten(-2)                                 # (..., 2m)
        twisting = c("select_tw").sum(-1) > 0
        alpha = torch.where(twisting, features[..., 3], torch.zeros_like(features[..., 3]))
        beta = torch.where(self.extends, features[..., 2], c("nominal_length").expand_as(alpha))
        h = torch.sqrt((alpha * c("helix_radius")) ** 2 + beta**2)
        lengths = rho @ c("displacement").mT + h @ c("path").mT
        twist = features[..., 3] @ c("select_tw")
        return torch.cat([lengths, twist], dim=-1)
