"""Slack-aware Clarke encoder for tendon robots (type-0 segments; docs/hardware.md, "The calibrated CC model").

The plain :class:`~dacr_learn.layers.ClarkeEncoder` (least squares, w = B⁺(q − q₀)) lets a slack tendon
pull the estimate. Here tendons are one-sided springs and the backbone an elastic rod: the Clarke coordinates
ρ (..., 2m) minimise E(ρ) = ½ c Σ_k ‖ρ⁽ᵏ⁾‖²/(l_k d_k²) + ½ Σ_i max(0, x_i + p − (Gρ)_i)²/L_i, G = −B_ρ (each
term: docs/hardware.md, "The calibrated CC model"; x_i [m] pulled positive). Commands with x = Gρ* and c → 0 give ρ*.

E is a strictly convex piecewise quadratic: :func:`solve_tendon_qp` minimises it by a semi-smooth Newton
(active-set) iteration, with gradients through the final linear solve (so c, p, the radii and the rotations can be
fitted); for fixed parameters :func:`active_set_gains` and :func:`select_active_set` solve it without iterations.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..checks import check_tensor
from ..clarke import joint_space_maps
from ..robot import RobotSpec

MIN_LOG_COMPLIANCE = -30.0  # c >= 1e-13 m²: keeps the linear systems regular when no tendon is taut


def check_type0(spec: RobotSpec) -> None:
    """ValueError unless every segment is type 0 (bending only)."""
    bad = [j for j, s in enumerate(spec.segments) if s.type != "0"]
    if bad:
        raise ValueError(f"segments{bad}.type: the slack-aware tendon encoder models bending-only (type 0) "
                         f"segments; got types {[spec.segments[j].type for j in bad]}")


def _rotations(angle: Tensor) -> Tensor:
    """(m,) angles → (m, 2, 2) rotation matrices."""
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)


def solve_tendon_qp(x: Tensor, g: Tensor, bend_w: Tensor, tendon_w: Tensor, iters: int = 30,
                    force_map: Tensor | None = None, load: Tensor | None = None) -> Tensor:
    """argmin_ρ ½ Σ bend_w ρ² + ½ Σ tendon_w·max(0, x − Gρ)², batched: x (B, N) commanded displacements
    (pretension included) [m], g (N, D) the map G, bend_w (D,), tendon_w (N,) positive weights → ρ (B, D).

    ``force_map`` (B, N, D): a map F of the tendon forces into the bending equations; the solution then satisfies
    bend_w·ρ = Fᵀ(tendon_w·max(0, x − Gρ)) (+ ``load`` (B, D), an external generalised force in the units of
    bend_w·ρ [m], e.g. gravity) instead of the energy minimum (F = G). Starts from the pulled tendons (x > 0);
    stops when the set of stretched tendons repeats (usually 2–5 iterations).
    """
    f = g if force_map is None else force_map
    active = x > 0
    eye_w = torch.diag_embed(bend_w)
    rho = x.new_zeros(x.shape[0], g.shape[1])
    for _ in range(iters):
        wa = tendon_w * active
        mat = eye_w + (f.mT * wa.unsqueeze(-2)) @ g
        rhs = (f.mT @ (wa * x).unsqueeze(-1)).squeeze(-1)
        rho = torch.linalg.solve(mat, rhs if load is None else rhs + load)
        new = (x - rho @ g.mT) > 0
        if torch.equal(new, active):
            break
        active = new
    return rho


MAX_ENUMERATED_TENDONS = 12  # 2^N sets: 4096 gains of (2m × N) at most


def active_set_gains(g: Tensor, bend_w: Tensor, tendon_w: Tensor) -> tuple[Tensor, Tensor]:
    """Every set S of stretched tendons and its linear solution map ρ_S = K_S x, for g (N, D), bend_w (D,),
    tendon_w (N,) as in :func:`solve_tendon_qp` (energy form): sets (2ᴺ, N) bool (row k: bit i of k ⇔ tendon i
    stretched) and K (2ᴺ, D, N) = (diag(bend_w) + Gᵀ W_S G)⁻¹ Gᵀ W_S, W_S = diag(tendon_w·1_S)."""
    n = g.shape[0]
    if n > MAX_ENUMERATED_TENDONS:
        raise ValueError(f"g: enumerating the active sets needs at most {MAX_ENUMERATED_TENDONS} tendons "
                         f"(2^N linear systems), got N = {n}")
    bits = torch.arange(n, device=g.device)
    sets = (torch.arange(2**n, device=g.device).unsqueeze(-1) >> bits) & 1 == 1
    gw = g.mT * (tendon_w * sets).unsqueeze(-2)                                   # (2ᴺ, D, N) = Gᵀ W_S
    return sets, torch.linalg.solve(torch.diag_embed(bend_w) + gw @ g, gw)


def select_active_set(residual: Tensor, sets: Tensor, tendon_w: Tensor) -> Tensor:
    """Index (...,) long of the consistent set: residual (..., 2ᴺ, N) = x − Gρ_S of every set, sets (2ᴺ, N) bool,
    tendon_w (N,); the set stretched exactly where the residual is positive (least tendon-weighted sign violation;
    ties to the lowest index, the fewest stretched tendons)."""
    sign = torch.where(sets, -1.0, 1.0).to(residual.dtype)                       # + where it must be ≤ 0
    violation = (torch.relu(residual * sign) * tendon_w.to(residual.dtype)).sum(-1)
    return violation.argmin(-1)


class SlackAwareEncoder(nn.Module):
    """Joint displacements (..., N) [m] → effective Clarke features (..., m, 4), in the convention of docs/design.md §3
    for the *nominal* spec ((ρ_re, ρ_im)·d_nominal/d_effective, β = l, α = 0): ``forward_kinematics(spec, features)``
    gives the effective shape. Learnable (float64): ``log_radius_scale`` (m,), d_k = d_k,nominal·exp(·); ``rotation``
    (m,) [rad] of each segment's joint angles; ``log_compliance`` (log c [m²]); ``pretension`` p [m]; with
    ``strain=True`` also ``pretension_strain`` s [m]: p_i = p + s·(L_i/L̄ − 1), L̄ the mean path length.
    """

    def __init__(self, spec: RobotSpec, compliance: float = 1e-6, pretension: float = 0.0, strain: bool = False):
        super().__init__()
        check_type0(spec)
        self.spec = spec
        m = spec.num_segments
        maps = joint_space_maps(spec)
        f64 = dict(dtype=torch.float64)
        self.register_buffer("g_nominal", -maps.displacement)                       # (N, 2m)
        lengths = torch.tensor([s.length for s in spec.segments], **f64)
        self.register_buffer("lengths", lengths)
        self.register_buffer("radius", torch.tensor([s.radius for s in spec.segments], **f64))
        self.register_buffer("path_length", maps.path @ lengths)                     # (N,)
        self.register_buffer("segment_of_joint", maps.path.flip(-1).argmax(-1).neg() + m - 1)
        self.log_radius_scale = nn.Parameter(torch.zeros(m, **f64))
        self.rotation = nn.Parameter(torch.zeros(m, **f64))
        self.log_compliance = nn.Parameter(torch.tensor(float(compliance), **f64).log())
        self.pretension = nn.Parameter(torch.tensor(float(pretension), **f64))
        self.strain = bool(strain)
        if self.strain:
            self.pretension_strain = nn.Parameter(torch.zeros((), **f64))

    def tendon_pretension(self) -> Tensor:
        """Pretension stretch of each tendon (N,) [m]: p, or p + s·(L_i/L̄ − 1) with ``strain``."""
        if not self.strain:
            return self.pretension.expand(self.path_length.shape)
        return self.pretension + self.pretension_strain * (self.path_length / self.path_length.mean() - 1)

    def effective_radius(self) -> Tensor:
        """(m,) effective radii d_k [m]."""
        return self.radius * self.log_radius_scale.exp()

    def displacement_map(self) -> Tensor:
        """G (N, 2m) with each segment's joint angles rotated by ``rotation``."""
        rot = _rotations(self.rotation)[self.segment_of_joint]                          # (N, 2, 2)
        m = self.spec.num_segments
        g = self.g_nominal.unflatten(-1, (m, 2))                                         # (N, m, 2)
        return (g.unsqueeze(-2) @ rot.mT.unsqueeze(1)).squeeze(-2).flatten(-2)

    def bend_weights(self) -> Tensor:
        """(2m,) weights c/(l_k d_k²) [1/m] of the bending energy, one per Clarke coordinate."""
        compliance = self.log_compliance.clamp(min=MIN_LOG_COMPLIANCE).exp()
        return (compliance / (self.lengths * self.effective_radius()**2)).repeat_interleave(2)

    def clarke(self, x: Tensor) -> Tensor:
        """Displacements (..., N) [m] → Clarke coordinates ρ (..., m, 2) [m] (at the effective radii)."""
        check_tensor(x, "displacements", (self.g_nominal.shape[0],))
        flat = x.reshape(-1, x.shape[-1]).to(torch.float64)
        pretension, g, bend_w, tendon_w = self.qp_terms()
        rho = solve_tendon_qp(flat + pretension, g, bend_w, tendon_w)
        return rho.reshape(*x.shape[:-1], -1, 2).to(x.dtype)

    def qp_terms(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The QP of :meth:`clarke` (float64): pretension stretch (N,) [m] added to the displacements, G (N, 2m),
        the bend weights (2m,) and the tendon weights 1/L_i (N,) of :func:`solve_tendon_qp`."""
        return self.tendon_pretension(), self.displacement_map(), self.bend_weights(), 1.0 / self.path_length

    def features_from_clarke(self, rho: Tensor) -> Tensor:
        """Clarke coordinates ρ (..., m, 2) [m] at the effective radii → features (..., m, 4) in the
        nominal-spec convention (ρ·d_nominal/d_effective, β = l, α = 0)."""
        rho = rho * (self.radius / self.effective_radius()).to(rho.dtype).unsqueeze(-1)
        beta = self.lengths.to(rho.dtype).expand(rho.shape[:-1])
        return torch.cat([rho, beta.unsqueeze(-1), torch.zeros_like(beta).unsqueeze(-1)], dim=-1)

    def forward(self, x: Tensor) -> Tensor:
        return self.features_from_clarke(self.clarke(x))
