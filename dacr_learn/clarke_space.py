"""The actuated Clarke feature space of a robot, for deployment, control and IK (float64 maps, docs/design.md §1).

- :class:`ClarkeFold`: joint vector q (..., N) → the encoder as one affine map of u = [q − q_ref, g]
  (q_ref the straight joint vector, subtracted first to keep float32 exact; g = √((α d)² + l²) − l the helix
  term of type-II segments), the actuated features f (..., D) and ∂f/∂q; type III adds the correction
  β = √(h² − (α d)²). The folded inference modules fold it into their first layer.
- :class:`DecoderJacobian`: ∂q/∂f of the Clarke decoder.
- :func:`clarke_limits`: the limits of the robot file on f (bend disk, length and twist ranges) as a
  :class:`~dacr_learn.limits.Limits` (saturation: ``project``, the inside-the-limits test: ``inside``).
- :class:`ClarkeSpace`: f ↔ q (encoder, decoder on the displacement constraint) and the limits.

Pure torch (no Lightning, no Rerun); built from a :class:`~dacr_learn.robot.RobotSpec`.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .checks import F64, to_f64
from .folding import affine_probe
from .layers import ClarkeDecoder, ClarkeEncoder
from .limits import Limits
from .models import actuated_columns, actuated_selection, actuated_to_features, fixed_features
from .robot import RobotSpec

__all__ = ["ClarkeFold", "ClarkeSpace", "DecoderJacobian", "clarke_limits", "feature_columns"]


def _affine_features(enc: ClarkeEncoder, sel: Tensor, has_g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Affine part of the actuated features, f_lin = E·u + e₀, u = [q − q_ref, g] (float64).

    Returns E (D, N + n_g), e₀ (D,), q_ref (N,). For a type-III segment the β column of f_lin
    holds the helix length h. Found by probing the affine map (:func:`~.folding.affine_probe`, exact).
    """
    enc = enc.to(F64)
    n, nl, m = enc.num_joints, enc.num_lengths, enc.num_segments
    l, ext = enc.nominal_length, enc.extends.to(F64)
    g_select = torch.eye(m, dtype=F64)[:, has_g]                         # (m, n_g)

    def f_lin(u: Tensor) -> Tensor:
        dl, tw, g = u[:, :nl], u[:, nl:n], u[:, n:] @ g_select.mT
        w = (dl + (l * ext - g) @ enc.path.mT) @ enc.actuated_pinv.mT
        rho = w[:, :2 * m].unflatten(-1, (m, 2))
        beta = l + (w[:, 2 * m:] - l @ enc.select_ext) @ enc.select_ext.mT
        alpha = tw @ enc.select_tw.mT
        return torch.cat([rho, beta.unsqueeze(-1), alpha.unsqueeze(-1)], -1).flatten(-2) @ sel.mT

    matrix, offset = affine_probe(f_lin, n + g_select.shape[1])
    q_ref = torch.cat([l @ enc.path.mT, torch.zeros(n - nl, dtype=F64)])
    return matrix.mT.contiguous(), offset, q_ref


def feature_columns(spec: RobotSpec, kind: str, segs: list[int]) -> list[int]:
    """Indices of the actuated feature columns of ``kind`` ("beta" | "alpha") of segments ``segs``."""
    index = {col: i for i, col in enumerate(actuated_columns(spec))}
    return [index[(k, kind)] for k in segs]


class ClarkeFold(nn.Module):
    """Joint vector → folded inputs u, actuated features f and ∂f/∂q (see the module docstring)."""

    def __init__(self, spec: RobotSpec):
        super().__init__()
        enc, segs = ClarkeEncoder(spec), spec.segments
        self.num_joints, self.num_lengths = spec.num_joints, spec.num_length_joints
        type2 = [k for k, s in enumerate(segs) if s.twists and not s.extends]
        type3 = [k for k, s in enumerate(segs) if s.twists and s.extends]
        twist_index = {k: i for i, k in enumerate(k for k, s in enumerate(segs) if s.twists)}
        sel = actuated_selection(spec).to(F64)
        e, e0, q_ref = _affine_features(enc, sel, torch.tensor([k in type2 for k in range(len(segs))]))
        self.has_g, self.has_type3 = bool(type2), bool(type3)
        self.register_buffer("E", e)
        self.register_buffer("e0", e0)
        self.register_buffer("q_ref", q_ref)
        g_index = [self.num_lengths + twist_index[k] for k in type2]
        for name, values, dtype in (("g_index", g_index, torch.long),
                                    ("g_radius", [segs[k].joint_radii[0] for k in type2], F64),
                                    ("g_length", [segs[k].length for k in type2], F64),
                                    ("beta3", feature_columns(spec, "beta", type3), torch.long),
                                    ("alpha3", feature_columns(spec, "alpha", type3), torch.long),
                                    ("radius3", [segs[k].joint_radii[0] for k in type3], F64)):
            # Empty index buffers are left out (None): torch.export would store them as broken groups.
            self.register_buffer(name, torch.tensor(values, dtype=dtype) if values else None)

    def inputs(self, q: Tensor) -> Tensor:
        """u = [q − q_ref, g] (..., N + n_g)."""
        dq = q - self.q_ref
        if not self.has_g:
            return dq
        ad2 = (q[..., self.g_index] * self.g_radius) ** 2
        return torch.cat([dq, ad2 / (torch.sqrt(ad2 + self.g_length**2) + self.g_length)], dim=-1)

    def type3_beta(self, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(h, α, β) of the type-III segments (B, n₃): β = sqrt(h² − (α r)²)."""
        h = u @ self.E[self.beta3].mT + self.e0[self.beta3]
        alpha = u @ self.E[self.alpha3].mT + self.e0[self.alpha3]
        ad2 = (alpha * self.radius3) ** 2
        return h, alpha, torch.sqrt(torch.clamp(h * h - ad2, min=torch.finfo(u.dtype).tiny))

    def features(self, u: Tensor) -> Tensor:
        """Actuated Clarke features f (..., D) [m, rad] from u, exactly as the encoder + selection."""
        f = u @ self.E.mT + self.e0
        if self.has_type3:
            f = f.index_copy(-1, self.beta3, self.type3_beta(u)[2])
        return f

    def jacobian(self, q: Tensor, u: Tensor) -> Tensor:
        """∂f/∂q (B, D, N) of the encoder (constant unless the robot twists)."""
        n = self.num_joints
        jac = self.E[:, :n].expand(q.shape[0], -1, -1)
        if self.has_g:
            h = u[:, n:] + self.g_length
            coef = q[:, self.g_index] * self.g_radius**2 / h                # ∂g/∂α
            jac = jac.index_add(-1, self.g_index, self.E[:, n:] * coef.unsqueeze(-2))
        if self.has_type3:
            h, alpha, beta = self.type3_beta(u)
            rows = (h / beta).unsqueeze(-1) * jac[:, self.beta3] \
                - (alpha * self.radius3**2 / beta).unsqueeze(-1) * jac[:, self.alpha3]
            jac = jac.index_copy(-2, self.beta3, rows)
        return jac


class DecoderJacobian(nn.Module):
    """∂q/∂f (B, N, D) of the Clarke decoder at actuated features f (B, D)."""

    def __init__(self, spec: RobotSpec):
        super().__init__()
        dec, sel = ClarkeDecoder(spec).to(F64), actuated_selection(spec).to(F64)
        segs, m = spec.segments, spec.num_segments
        ext, tw = [k for k, s in enumerate(segs) if s.extends], [k for k, s in enumerate(segs) if s.twists]
        d = sel.shape[0]
        pick_beta, pick_alpha = torch.zeros(d, m, dtype=F64), torch.zeros(d, m, dtype=F64)
        pick_beta[feature_columns(spec, "beta", ext), ext] = 1.0
        pick_alpha[feature_columns(spec, "alpha", tw), tw] = 1.0
        const = torch.zeros(spec.num_joints, d, dtype=F64)
        rho_cols = [c for c in range(d) if not (pick_beta[c].any() or pick_alpha[c].any())]
        const[:spec.num_length_joints, rho_cols] = dec.displacement
        const[spec.num_length_joints:] = pick_alpha.mT[tw]
        path = torch.zeros(spec.num_joints, d, dtype=F64)
        path[:spec.num_length_joints] = dec.path @ (pick_beta + pick_alpha).mT
        self.register_buffer("pick_beta", pick_beta)
        self.register_buffer("pick_alpha", pick_alpha)
        self.register_buffer("fixed_length", dec.nominal_length * (~dec.extends))
        self.register_buffer("radius", dec.helix_radius)
        self.register_buffer("const", const)
        self.register_buffer("path", path)

    def forward(self, f: Tensor) -> Tensor:
        beta, alpha = f @ self.pick_beta + self.fixed_length, f @ self.pick_alpha
        h = torch.sqrt((alpha * self.radius) ** 2 + beta**2)
        coef = (beta / h) @ self.pick_beta.mT + (alpha * self.radius**2 / h) @ self.pick_alpha.mT
        return self.const + self.path * coef.unsqueeze(-2)


def clarke_limits(spec: RobotSpec) -> Limits:
    """The limits of a robot's actuated features (``models.actuated_columns`` order): per segment a disk
    ‖(ρ_re, ρ_im)‖ ≤ d·bend, boxes for β (length range) and α (twist range); scales d·bend and the half-ranges."""
    parts = []
    for k, name in actuated_columns(spec):
        seg = spec.segments[k]
        if name == "rho_re":
            parts.append(Limits.disk(seg.bend * seg.radius, (f"segments[{k}].rho_re", f"segments[{k}].rho_im")))
        elif name in ("beta", "alpha"):
            lo, hi = seg.length_range if name == "beta" else seg.twist_range
            parts.append(Limits.boxes([lo], [hi], (f"segments[{k}].{name}",)))
    return Limits.concatenate(*parts)


class ClarkeSpace:
    """Actuated Clarke features f (..., D) ↔ joint vectors q (..., N) of a robot, and their ``limits`` (float64)."""

    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self.encoder, self.decoder = ClarkeEncoder(spec).to(F64), ClarkeDecoder(spec).to(F64)
        self.fold = ClarkeFold(spec)                       # the encoder as one affine map (+ helix terms)
        self.selection = actuated_selection(spec).to(F64)
        self.base = fixed_features(spec, F64)
        self.linear = not any(s.twists for s in spec.segments)   # then the decoder is affine: q = A·f + c
        if self.linear:
            straight = self.fold.e0                               # features of the nominal straight robot
            self.dec_matrix = DecoderJacobian(spec)(straight)
            self.dec_offset = self._decode(straight) - self.dec_matrix @ straight
        self.limits = clarke_limits(spec)

    def features(self, q: Tensor) -> Tensor:
        """Joint vector (..., N) → actuated features (..., D) (the least-squares projection for noisy q)."""
        return self.fold.features(self.fold.inputs(to_f64(q)))

    def _decode(self, f: Tensor) -> Tensor:
        return self.decoder(actuated_to_features(f, self.selection, self.base))

    def joints(self, f: Tensor) -> Tensor:
        """Actuated features (..., D) → joint vector (..., N) on the displacement constraint."""
        f = to_f64(f)
        return torch.addmm(self.dec_offset, f, self.dec_matrix.mT) if self.linear and f.dim() == 2 else (
            self.dec_offset + f @ self.dec_matrix.mT if self.linear else self._decode(f))
