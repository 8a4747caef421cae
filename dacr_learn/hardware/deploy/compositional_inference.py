"""Inference modules of a saved compositional hardware model (registry ``cc_compositional_residual``).

The counterparts of :class:`~.inference.HardwareFK` / :class:`~.inference.HardwareJacobian` for an
ensemble of K :class:`~.compositional_model.CCCompositionalResidual` members; plain nn.Modules with
every constant in buffers, exportable with torch.export (``python -m dacr_learn.export``):

- :class:`CompositionalHardwareFK`: servo (B, S) [mm, checkpoint column order] → tip (B, 3) [m,
  motion-capture frame] = the ensemble mean, tip_std (B, 3) [m] = the model's σ
  (:meth:`~.checkpoint.HardwareModel.sigma_of`: floor, ensemble spread and bend terms, the same buffer
  and formula as HardwareFK).
- :class:`CompositionalHardwareJacobian`: servo (B, S) → tip (B, 3), J = ∂tip/∂servo (B, 3, S) [m/mm]:
  forward-mode tangents written out (∂ρ/∂servo of the active set's affine map, through the networks,
  :func:`twist_exp_and_tangent`, :func:`~.inference.twist_pose_derivative_times` and the chain's prefixes
  and suffixes, :meth:`CompositionalHardwareFK.tips_and_rho_jacobian`); the torch.func transforms (jacrev,
  jacfwd) of the FK do not trace with torch.export (torch 2.13).

Pipeline: servo → ρ per segment (the slack-aware encoder's active-set fast path of HardwareFK: the
same buffers, :func:`~.inference.active_set_maps`, and the same method, HardwareFK.clarke) → CC
segment poses T_k^CC(ρ_k) (:func:`~.inference.twist_segment_poses`) → each member's correction exp(ξ_k^),
ξ_k = s·f_θ(z_k, c_k) (the K networks batched: weights (K, in, out); the feature normaliser kept as
(ρ − μ)/σ with the standardised fixed columns β = l, α = 0 precomputed per segment in the member's
own dtype; the twist scale s, the torsion mask, the translation unit L_s and, in the FK path, the map
ξ ↦ ξ^ folded into the output layer and the skip; exp(ξ^) = I + ξ^ + fξ^² + gξ^³,
:func:`exp_of_twist_matrix`) → base pose · T_1 ⋯ T_m · marker → ensemble mean and σ. No history: the
model is static.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ...kinematics import effective_features
from ...lie import exp_of_twist_matrix, hat_map, pose_from_parts, twist_exp_and_tangent
from .checkpoint import HardwareModel
from .inference import (
    HardwareFK,
    active_set_maps,
    chain_prefix_suffix,
    chained_marker_point,
    segment_twists,
    sigma_coefficients,
    silu_linear_rows,
    twist_pose_derivative_times,
    twist_pose_terms,
    twist_segment_poses,
)

_F64 = torch.float64


def _check_servo(servo: Tensor, num_servos: int) -> None:
    if servo.dim() != 2 or servo.shape[-1] != num_servos:
        raise ValueError(f"servo: expected shape (B, {num_servos}) [mm], got {tuple(servo.shape)}")


def _stacked_networks(members) -> tuple[dict[str, Tensor], nn.Module, str]:
    """The K members' per-segment networks side by side (float64 buffers), their activation and context.

    ``rho_mean``/``rho_std`` (K, 1, 2) and ``z_fixed`` (K, m, 2): the normaliser (ρ part; the fixed columns
    standardised once, in the member's dtype, as training saw them); ``w{i}`` (K, in, out), ``b{i}`` (K, 1, out)
    the linear layers of f_θ; ``skip`` (K, in, 6); the last layer and skip scaled by the twist mask and, for
    the translation rows, the segment length unit L_s, so that ξ = a_last + z·skip directly."""
    fks = [m.fk for m in members]
    context, acts = fks[0].front.context, {type(l) for fk in fks for l in fk.net if not isinstance(l, nn.Linear)}
    if len(acts) != 1 or any(fk.front.context != context or fk.rotation != "twist" or fk.units != "metric"
                             for fk in fks):
        raise ValueError(f"members: expected one activation, one context, the twist head and metric units, got "
                         f"activations {sorted(a.__name__ for a in acts)}, contexts "
                         f"{[fk.front.context for fk in fks]}, heads {[fk.rotation for fk in fks]}, "
                         f"units {[fk.units for fk in fks]}")
    spec = members[0].spec
    out: dict[str, Tensor] = {}
    with torch.no_grad():
        dtype = fks[0].skip.weight.dtype
        fixed = effective_features(spec, torch.zeros(1, spec.num_segments, 4, dtype=dtype))
        out["z_fixed"] = torch.stack([fk.front.norm(fixed)[0, :, 2:] for fk in fks]).to(_F64)
        out["rho_mean"] = torch.stack([fk.front.norm.mean[:2] for fk in fks]).to(_F64).unsqueeze(1)
        out["rho_std"] = torch.stack([fk.front.norm.std[:2] for fk in fks]).to(_F64).unsqueeze(1)
        out["context_matrix"] = fks[0].front.context_matrix.to(_F64)
        unit = torch.stack([m.twist_mask.to(_F64) for m in members])                      # (K, 6)
        unit[:, :3] *= torch.stack([fk.length_scale[:1].to(_F64) for fk in fks])     # metric: one L_s per member
        layers = [[l for l in fk.net if isinstance(l, nn.Linear)] for fk in fks]
        for i in range(len(layers[0])):
            scale = unit.unsqueeze(1) if i == len(layers[0]) - 1 else 1.0
            out[f"w{i}"] = torch.stack([ls[i].weight for ls in layers]).to(_F64).mT * scale
            out[f"b{i}"] = torch.stack([ls[i].bias for ls in layers]).to(_F64).unsqueeze(1) * scale
        out["skip"] = torch.stack([fk.skip.weight for fk in fks]).to(_F64).mT * unit.unsqueeze(1)
        last = len(layers[0]) - 1        # the FK path: output layer and skip give the 4 × 4 twist matrix ξ^ directly
        to_matrix = hat_map()
        out.update({"w_hat": out[f"w{last}"] @ to_matrix, "b_hat": out[f"b{last}"] @ to_matrix,
                    "skip_hat": out["skip"] @ to_matrix})
    return out, acts.pop()(), context


class CompositionalHardwareFK(nn.Module):
    """Servo commands (B, S) [mm] → (tip (B, 3) [m], tip_std (B, 3) [m]) of a compositional hardware model."""

    history = False

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        if not model.compositional:
            raise ValueError(f"model: expected CCCompositionalResidual members, got "
                             f"{[type(m).__name__ for m in model.members]} (use inference.HardwareFK)")
        spec, cc = model.spec, model.cc
        self.num_segments, self.num_servos, self.ensemble = spec.num_segments, len(model.servo_ids), len(model.members)
        nets, self.activation, self.context = _stacked_networks(model.members)
        self.layers = sum(1 for k in nets if k[0] == "w" and k[1:].isdigit())    # linear layers of f_θ
        with torch.no_grad():
            buffers = {**active_set_maps(model), **nets,
                       "base_pose": pose_from_parts(cc.base_rotation(), cc.base_translation),
                       "tip_marker": torch.cat([cc.marker_offset(), torch.ones(1, dtype=_F64)]),   # homogeneous
                       "sigma_coefficients": sigma_coefficients(model),
                       "radius": torch.tensor([s.radius for s in spec.segments], dtype=_F64),
                       "length": torch.tensor([s.length for s in spec.segments], dtype=_F64)}
            buffers.update(segment_twists(buffers["radius"], buffers["length"]))
        for name, value in buffers.items():   # contiguous: torch.export.save stores whole tensors, not views
            self.register_buffer(name, value.detach().contiguous())    # float64 until the affine part is folded
        self.hidden_width = self.w0.shape[-1]
        with torch.no_grad():
            affine_map, affine_offset = self.affine_part(self.skip_hat)
        self.register_buffer("affine_map", affine_map)
        self.register_buffer("affine_offset", affine_offset)
        self.to(dtype)
        self.spec = spec

    def affine_part(self, skip: Tensor) -> tuple[Tensor, Tensor]:
        """The first layer's pre-activation and the skip term z·skip of every member (B, K, m, H + E) are affine
        in ρ (standardisation, fixed columns and context are): their map (2m, K·m·(H + E)) and offset, from the
        module evaluated at ρ = 0 and the 2m unit vectors (exact for an affine function; float64 at build).
        ``skip`` (K, C, E): ``skip_hat`` (ξ^, E = 16, the FK path) or ``skip`` (ξ, E = 6, the Jacobian)."""
        m, dtype = self.num_segments, self.w0.dtype
        basis = torch.cat([torch.zeros(1, 2 * m, dtype=dtype), torch.eye(2 * m, dtype=dtype)]).unflatten(-1, (m, 2))
        z = self.inputs(basis)                                                            # (1 + 2m, K, m, C)
        both = torch.cat([z @ self.w0 + self.b0, z @ skip], -1)                           # (1 + 2m, K, m, H + E)
        return (both[1:] - both[:1]).flatten(1), both[0].flatten()

    clarke = HardwareFK.clarke          # servo → ρ (B, m, 2) [+ ∂ρ/∂servo]: the same buffers as HardwareFK's
    mean_std = HardwareFK.mean_std      # ensemble mean and the σ model, the same buffer and formula

    def inputs(self, rho: Tensor) -> Tensor:
        """Network inputs (B, K, m, C) of every member: standardised features and context of ρ (B, m, 2)."""
        z_rho = (rho.unsqueeze(1) - self.rho_mean) / self.rho_std                          # (B, K, m, 2)
        return self.context_of(torch.cat([z_rho, self.z_fixed.expand(rho.shape[0], -1, -1, -1)], -1))

    def context_of(self, z: Tensor) -> Tensor:
        """Standardised features z (B, K, m, 4) with the context appended (CompositionalFK's ``with_context``)."""
        if self.context == "none":
            return z
        extra = self.context_matrix.expand(*z.shape[:-2], -1, -1) if self.context == "segment" else (
            self.context_matrix @ z)
        return torch.cat([z, extra], -1)

    def corrections(self, rho: Tensor) -> Tensor:
        """Each member's correction exp(ξ_k^) of every segment (B, K, m, 4, 4) at ρ (B, m, 2) [m]: the affine
        part (first layer and skip, :meth:`affine_part`) in one product, the hidden and output layers as
        batched products over the members (K, B·m, ·) (v6 default's AOTI runner 46.0 → 41.3 µs)."""
        k, m, h = self.ensemble, self.num_segments, self.hidden_width
        pre = torch.addmm(self.affine_offset, rho.flatten(1), self.affine_map).view(-1, k, m, h + 16)
        a = pre[..., :h].transpose(0, 1).reshape(k, -1, h)                                # (K, B·m, H)
        for i in range(1, self.layers - 1):
            a = torch.baddbmm(getattr(self, f"b{i}"), self.activation(a), getattr(self, f"w{i}"))
        xi_hat = torch.baddbmm(self.b_hat, self.activation(a), self.w_hat)                # (K, B·m, 16)
        xi_hat = xi_hat.view(k, -1, m, 16).transpose(0, 1) + pre[..., h:]                 # ξ^ (B, K, m, 16)
        return exp_of_twist_matrix(xi_hat.unflatten(-1, (4, 4)))

    def tips(self, rho: Tensor) -> Tensor:
        """Every member's tip (B, K, 3) [m, motion-capture frame] at ρ (B, m, 2) [m]."""
        cc = twist_segment_poses(rho, self.twist_map, self.twist_offset, self.half_turns, self.eye4)  # (B, m, 4, 4)
        return chained_marker_point(self.base_pose, cc.unsqueeze(1) @ self.corrections(rho), self.tip_marker)

    def tips_and_rho_jacobian(self, rho: Tensor, affine_map: Tensor, affine_offset: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`tips` (B, K, 3) and ∂tips/∂ρ (B, K, 2m, 3) (forward mode along the 2m Clarke coordinates,
        written out: torch.export does not trace torch.func transforms of this model); ``affine_map``/``_offset``:
        :meth:`affine_part` of ``skip`` (ξ, 6 columns).

        The first layer and the skip term are affine in ρ, so their tangents are the map's rows; the value and
        its 2m tangents go through each further layer as 1 + 2m stacked rows of one product per layer, batched
        over the members (bias on the value row only; SiLU' scales the tangent rows). The corrections and their
        tangents come from :func:`twist_exp_and_tangent`; the chain is differentiated with prefixes and suffixes
        (:func:`~.inference.chain_prefix_suffix`): ∂tip = P_k · (∂T_k^CC · C_k + T_k^CC · ∂C_k) · v_k."""
        b, m, k, h = rho.shape[0], self.num_segments, self.ensemble, self.hidden_width
        t = 2 * m
        pre = torch.addmm(affine_offset, rho.flatten(1), affine_map).view(b, 1, k, m, -1)
        rows = torch.cat([pre, affine_map.view(1, t, k, m, -1).expand(b, -1, -1, -1, -1)], 1)  # (B, 1 + T, K, m, H + 6)
        a = rows[..., :h].permute(2, 0, 3, 1, 4).reshape(k, b * m, 1 + t, h)
        for i in range(1, self.layers):
            a = silu_linear_rows(a, getattr(self, f"w{i}"), getattr(self, f"b{i}"))
        xi = a.view(k, b, m, 1 + t, 6).permute(1, 0, 2, 3, 4) + rows[..., h:].permute(0, 2, 3, 1, 4)  # (B,K,m,1+T,6)
        corr, dcorr = twist_exp_and_tangent(xi[..., 0, :], xi[..., 1:, :])                 # (B,K,m,4,4), (B,K,m,T,4,4)
        cc, terms = twist_pose_terms(rho, self.twist_map, self.twist_offset, self.radius, self.eye4)
        poses = cc.unsqueeze(1) @ corr                                                     # (B, K, m, 4, 4)
        p, v = chain_prefix_suffix(self.base_pose, poses, self.tip_marker)                 # (B,K,m,4,4), (B,K,m,4)
        tip = (p[..., -1, :3, :] @ (poses[..., -1, :, :] @ v[..., -1, :].unsqueeze(-1))).squeeze(-1)
        terms = tuple(x.unsqueeze(1) for x in terms[:-1]) + terms[-1:]                      # members broadcast
        dcc = twist_pose_derivative_times(terms, (corr @ v.unsqueeze(-1)).squeeze(-1))     # ∂T^CC·C·v (B,K,m,2,4)
        d_own = (p[..., :3, :].unsqueeze(-3) @ dcc.unsqueeze(-1)).squeeze(-1).flatten(2, 3)  # (B, K, 2m, 3)
        dcv = (dcorr @ v[..., None, :, None]).squeeze(-1)                                  # ∂C·v (B, K, m, T, 4)
        d_corr = ((p @ cc.unsqueeze(1))[..., :3, :].unsqueeze(-3) @ dcv.unsqueeze(-1)).squeeze(-1).sum(2)  # (B,K,T,3)
        return tip, d_own + d_corr

    def forward(self, servo: Tensor) -> tuple[Tensor, Tensor]:
        _check_servo(servo, self.num_servos)
        rho = self.clarke(servo, derivative=False)[0]
        return self.mean_std(self.tips(rho), rho)


class CompositionalHardwareJacobian(nn.Module):
    """Servo (B, S) [mm] → (tip (B, 3) [m], J = ∂tip/∂servo (B, 3, S) [m/mm]) of the ensemble-mean tip."""

    history = False

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.fk = CompositionalHardwareFK(model, dtype)
        with torch.no_grad():                         # the affine part with the 6-column skip ξ (float64 at build)
            affine_map, affine_offset = CompositionalHardwareFK(model, _F64).affine_part(self.fk.skip.to(_F64))
        self.register_buffer("affine_map", affine_map.to(dtype))
        self.register_buffer("affine_offset", affine_offset.to(dtype))

    def forward(self, servo: Tensor) -> tuple[Tensor, Tensor]:
        """∂tip/∂servo = ∂tip/∂ρ · ∂ρ/∂servo: 2m tangents through the model (fewer than S servos)."""
        fk = self.fk
        _check_servo(servo, fk.num_servos)
        rho, drho = fk.clarke(servo)                                                       # (B, m, 2), (B, m, 2, S)
        tips, dtips = fk.tips_and_rho_jacobian(rho, self.affine_map, self.affine_offset)   # (B, K, 3), (B, K, 2m, 3)
        return tips.mean(1), dtips.mean(1).mT @ drho.flatten(1, 2)
