"""Inference modules of a saved compositional hardware model (registry ``cc_compositional_residual``).

The counterparts of :class:`~.inference.HardwareFK` / :class:`~.inference.HardwareJacobian` (the same inputs,
outputs and σ; plain nn.Modules, exported alike) for K :class:`~.compositional_model.CCCompositionalResidual` members.

Pipeline: servo → ρ (HardwareFK's active-set fast path, :func:`~.inference.active_set_maps`) → CC segment
poses (:func:`~.inference.cc_segment_poses`) → each member's correction exp(ξ_k^) (the K networks batched,
twist scale, torsion mask and L_s folded into the output layer and skip) → base pose · T_1 ⋯ T_m · marker →
ensemble mean and σ. No history: the model is static.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ...checks import F64
from ...compositional import append_context
from ...folding import activation_name, affine_probe, linear_layers, stacked_linear, tangent_rows
from ...kinematics import cc_twist, effective_features
from ...lie import twist_chain_jacobian, twist_exp
from .checkpoint import HardwareModel
from .inference import HardwareFK, cc_segment_poses, cc_twist_directions, chained_marker_point, model_constants


def _check_servo(servo: Tensor, num_servos: int) -> None:
    if servo.dim() != 2 or servo.shape[-1] != num_servos:
        raise ValueError(f"servo: expected shape (B, {num_servos}) [mm], got {tuple(servo.shape)}")


def _stacked_networks(members) -> tuple[dict[str, Tensor], str, str]:
    """The K members' per-segment networks side by side (float64 buffers), their activation and context:
    ``rho_mean``/``rho_std`` (K, 1, 2), ``z_fixed`` (K, m, 2) (the standardised fixed columns, in the member's dtype),
    ``w{i}`` (K, in, out), ``b{i}`` (K, 1, out) (:func:`~dacr_learn.folding.stacked_linear`) and ``skip`` (K, in, 6),
    the last layer and skip scaled by the twist mask and L_s, so that ξ = a_last + z·skip directly.
    """
    fks = [m.fk for m in members]
    context = fks[0].front.context
    if any(fk.front.context != context or fk.rotation != "twist" or fk.units != "metric" for fk in fks):
        raise ValueError(f"members: expected one context, the twist head and metric units, got contexts "
                         f"{[fk.front.context for fk in fks]}, heads {[fk.rotation for fk in fks]}, "
                         f"units {[fk.units for fk in fks]}")
    activation = activation_name([fk.net for fk in fks])
    spec = members[0].spec
    out: dict[str, Tensor] = {}
    with torch.no_grad():
        dtype = fks[0].skip.weight.dtype
        fixed = effective_features(spec, torch.zeros(1, spec.num_segments, 4, dtype=dtype))
        out["z_fixed"] = torch.stack([fk.front.norm(fixed)[0, :, 2:] for fk in fks]).to(F64)
        out["rho_mean"] = torch.stack([fk.front.norm.mean[:2] for fk in fks]).to(F64).unsqueeze(1)
        out["rho_std"] = torch.stack([fk.front.norm.std[:2] for fk in fks]).to(F64).unsqueeze(1)
        out["context_matrix"] = fks[0].front.context_matrix.to(F64)
        unit = torch.stack([m.twist_mask.to(F64) for m in members])                      # (K, 6)
        unit[:, :3] *= torch.stack([fk.length_scale[:1].to(F64) for fk in fks])     # metric: one L_s per member
        layers = [linear_layers(fk.net) for fk in fks]
        last = len(layers[0]) - 1
        for i in range(len(layers[0])):
            scale = unit.unsqueeze(1) if i == last else 1.0
            out[f"w{i}"], out[f"b{i}"] = stacked_linear([ls[i] for ls in layers], scale)
        out["skip"] = torch.stack([fk.skip.weight for fk in fks]).to(F64).mT * unit.unsqueeze(1)
    return out, activation, context


class CompositionalHardwareFK(nn.Module):
    """Servo commands (B, S) [mm] → (tip (B, 3) [m], tip_std (B, 3) [m]) of a compositional hardware model."""

    history = False

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        if not model.compositional:
            raise ValueError(f"model: expected CCCompositionalResidual members, got "
                             f"{[type(m).__name__ for m in model.members]} (use inference.HardwareFK)")
        spec = model.spec
        self.num_segments, self.num_servos, self.ensemble = spec.num_segments, len(model.servo_ids), len(model.members)
        nets, self.activation, self.context = _stacked_networks(model.members)
        self.layers = sum(1 for k in nets if k[0] == "w" and k[1:].isdigit())    # linear layers of f_θ
        with torch.no_grad():
            buffers = {**model_constants(model), **nets}
            # ∂ξ_k^CC along all 2m coordinates (m, 2m, 6): segment k's two directions, zero elsewhere
            eye = torch.eye(spec.num_segments, dtype=F64)[:, :, None, None]
            buffers["cc_directions"] = (eye * cc_twist_directions(buffers["radius"])).flatten(1, 2)
        for name, value in buffers.items():   # contiguous: torch.export.save stores whole tensors, not views
            self.register_buffer(name, value.detach().contiguous())    # float64 until the affine part is folded
        self.hidden_width = self.w0.shape[-1]
        with torch.no_grad():
            affine_map, affine_offset = self.affine_part()
        self.register_buffer("affine_map", affine_map)
        self.register_buffer("affine_offset", affine_offset)
        self.to(dtype)
        self.spec = spec

    def affine_part(self) -> tuple[Tensor, Tensor]:
        """The first layer's pre-activation and the skip term z·skip of every member (B, K, m, H + 6) are affine
        in ρ (standardisation, fixed columns and context are): their map (2m, K·m·(H + 6)) and offset, probed at
        ρ = 0 and the 2m unit vectors (:func:`~dacr_learn.folding.affine_probe`; float64 at build)."""
        def first_and_skip(rho: Tensor) -> Tensor:
            z = self.inputs(rho.unflatten(-1, (self.num_segments, 2)))                   # (P, K, m, C)
            return torch.cat([z @ self.w0 + self.b0, z @ self.skip], -1)
        return affine_probe(first_and_skip, 2 * self.num_segments, self.w0.dtype)

    clarke = HardwareFK.clarke          # servo → ρ (B, m, 2) [+ ∂ρ/∂servo]: the same buffers as HardwareFK's
    mean_std = HardwareFK.mean_std      # ensemble mean and the σ model, the same buffer and formula

    def inputs(self, rho: Tensor) -> Tensor:
        """Network inputs (B, K, m, C) of every member: standardised features and context of ρ (B, m, 2)."""
        z_rho = (rho.unsqueeze(1) - self.rho_mean) / self.rho_std                          # (B, K, m, 2)
        z = torch.cat([z_rho, self.z_fixed.expand(rho.shape[0], -1, -1, -1)], -1)
        return append_context(z, self.context, self.context_matrix)

    def twists(self, rho: Tensor, tangents: bool = False) -> Tensor:
        """Each member's twist ξ_k (B, K, m, 1, 6) of every segment at ρ (B, m, 2) [m], with its 2m tangents along
        the Clarke coordinates (B, K, m, 1 + 2m, 6) if ``tangents``: the affine part (first layer and skip,
        :meth:`affine_part`) in one product, its tangents the map's rows; the further layers batched over the
        members (K, B·m, ·) as stacked rows (:func:`~dacr_learn.folding.tangent_rows`)."""
        b, m, k, h = rho.shape[0], self.num_segments, self.ensemble, self.hidden_width
        rows = torch.addmm(self.affine_offset, rho.flatten(1), self.affine_map).view(b, 1, k, m, -1)
        if tangents:
            rows = torch.cat([rows, self.affine_map.view(1, 2 * m, k, m, -1).expand(b, -1, -1, -1, -1)], 1)
        n = rows.shape[1]                                                                  # rows (B, n, K, m, H + 6)
        a = rows[..., :h].permute(2, 0, 3, 1, 4).reshape(k, b * m, n, h)
        a = tangent_rows(a, [(getattr(self, f"w{i}"), getattr(self, f"b{i}")) for i in range(1, self.layers)],
                         self.activation)
        return a.view(k, b, m, n, 6).transpose(0, 1) + rows[..., h:].permute(0, 2, 3, 1, 4)

    def tips(self, rho: Tensor) -> Tensor:
        """Every member's tip (B, K, 3) [m, motion-capture frame] at ρ (B, m, 2) [m]: the CC poses times each
        member's corrections exp(ξ_k^) (the kernel's :func:`~dacr_learn.lie.twist_exp`), chained."""
        cc = cc_segment_poses(rho, self.radius, self.length)                             # (B, m, 4, 4)
        corrections = twist_exp(self.twists(rho)[..., 0, :])                              # (B, K, m, 4, 4)
        return chained_marker_point(self.base_pose, cc.unsqueeze(1) @ corrections, self.tip_marker)

    def tips_and_rho_jacobian(self, rho: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`tips` (B, K, 3) and ∂tips/∂ρ (B, K, 2m, 3): the chain base · T_1^CC·C_1 ⋯ T_m^CC·C_m · marker
        differentiated by the kernel (:func:`~dacr_learn.lie.twist_chain_jacobian`), each CC factor along its own
        two coordinates, each correction along all 2m (:meth:`twists`)."""
        b, k, t = rho.shape[0], self.ensemble, 2 * self.num_segments
        xi = self.twists(rho, tangents=True)                                               # (B, K, m, 1 + T, 6)
        xi_cc = cc_twist(rho / self.radius.unsqueeze(-1), self.length).unsqueeze(1).expand(-1, k, -1, -1)
        # interleaved factors T_1^CC, C_1, …, T_m^CC, C_m: twists (B, K, 2m, 6) and tangents (B, K, 2m, T, 6)
        twists = torch.stack([xi_cc, xi[..., 0, :]], 3).flatten(2, 3)
        tangents = torch.stack([self.cc_directions.expand(b, k, -1, -1, -1), xi[..., 1:, :]], 3).flatten(2, 3)
        tip, jac = twist_chain_jacobian(twists, tangents, base=self.base_pose, point=self.tip_marker[:3])
        return tip[..., :3, 3], jac[..., :3, :].unflatten(-1, (t, t)).sum(-2).mT

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

    def forward(self, servo: Tensor) -> tuple[Tensor, Tensor]:
        """∂tip/∂servo = ∂tip/∂ρ · ∂ρ/∂servo: 2m tangents through the model (fewer than S servos)."""
        fk = self.fk
        _check_servo(servo, fk.num_servos)
        rho, drho = fk.clarke(servo)                                                       # (B, m, 2), (B, m, 2, S)
        tips, dtips = fk.tips_and_rho_jacobian(rho)                                        # (B, K, 3), (B, K, 2m, 3)
        return tips.mean(1), dtips.mean(1).mT @ drho.flatten(1, 2)
