"""Inference modules of a fitted hardware model for controllers: servo commands [mm] → tip [m], Jacobian.

Built from a :class:`~.checkpoint.HardwareModel` (the CC Clarke-residual family, an ensemble of K members); plain
nn.Modules with every constant folded into buffers, exportable with torch.export (inputs and outputs: docs/export.md,
"Hardware models"). Tip: the ensemble mean, motion-capture frame; for a history model J holds the state fixed.

Pipeline (float32 by default): servo → ρ by the slack-aware encoder's QP solved by active-set enumeration
with the servo map folded in (:func:`~.slack.active_set_gains`: the same minimiser as
:func:`~.slack.solve_tendon_qp`, no iterations or linear solves; N ≤ 12 tendons) → [play operator step] →
per-member correction Δρ (batched over members) → CC segment poses (:mod:`dacr_learn.lie`) → tip.

History models run causally: ``state`` is the play operator's state (the previous call's output); start
a sequence with :meth:`HardwareFK.initial_state` of the first command. Row by row this gives the model's
batch predictions.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ...checks import F64
from ...folding import activation_name, linear_layers, stacked_linear, tangent_rows
from ...kinematics import cc_transform, cc_twist
from ...lie import chain_products, components, pose_from_parts, twist_chain_jacobian
from ..learned import RESIDUAL_RHO_SCALE
from ..slack import active_set_gains
from .checkpoint import HardwareModel


def cc_segment_poses(rho: Tensor, radius: Tensor, length: Tensor) -> Tensor:
    """CC segment poses (..., m, 4, 4) of ρ (..., m, 2) [m] for segments of radius d (m,) and length β (m,) [m]:
    the kernel's exponential of the CC twist, :func:`~dacr_learn.kinematics.cc_transform` (ρ/d, β)."""
    return cc_transform(rho / radius.unsqueeze(-1), length)


def cc_twist_directions(radius: Tensor) -> Tensor:
    """∂ξ/∂ρ (m, 2, 6) of the CC twists ξ_k = :func:`~dacr_learn.kinematics.cc_twist` (ρ_k/d_k, β_k), which are
    linear in ρ: cc_twist(e_j/d_k, 0) (the tangent directions of :func:`cc_tip_and_jacobian`)."""
    eye = torch.eye(2, dtype=radius.dtype, device=radius.device)
    return cc_twist(eye / radius[:, None, None], torch.zeros(radius.shape[0], 2, dtype=radius.dtype))


def chained_marker_point(base_pose: Tensor, poses: Tensor, tip_marker: Tensor) -> Tensor:
    """Marker point (..., 3) [m, motion-capture frame] = base pose (4, 4) · T₁ ⋯ T_m · (marker, 1) of segment
    poses (..., m, 4, 4), tip_marker (4,) homogeneous (:func:`~dacr_learn.lie.chain_products`)."""
    return (base_pose @ chain_products(poses, tip_only=True) @ tip_marker)[..., :3]


def cc_tip_and_jacobian(rho: Tensor, radius: Tensor, length: Tensor, directions: Tensor, base_pose: Tensor,
                        tip_marker: Tensor) -> tuple[Tensor, Tensor]:
    """ρ (..., m, 2) [m] → marker point base · T₁ ⋯ T_m · marker (..., 3) [m] and ∂tip/∂ρ (..., m, 2, 3): the kernel's
    exponential along ``directions`` (:func:`cc_twist_directions`) and its chain rule with the base pose and the
    marker as fixed ends (:func:`~dacr_learn.lie.twist_chain_jacobian`)."""
    u = components(rho / radius.unsqueeze(-1))                                        # u_x, u_y (..., m)
    dw = directions[..., 3:5].permute(1, 2, 0).unflatten(-1, (*[1] * (rho.dim() - 2), -1))   # dω_x, dω_y (T, 1.., m)
    xi, dxi = (None, None, length, -u[1], u[0], None), (None, None, None, dw[:, 0], dw[:, 1], None)   # zeros skipped
    tip, jac = twist_chain_jacobian(xi, dxi, base=base_pose, point=tip_marker[:3])
    return tip[..., :3, 3], jac[..., :3, :].unflatten(-1, (rho.shape[-2], 2)).movedim(-3, -1)


SIGMA_TERMS_EXPORTED = ("ensemble", "bend")


def model_constants(model: HardwareModel) -> dict[str, Tensor]:
    """The float64 constants of both hardware FKs: :func:`active_set_maps`, the segments' ``radius`` and ``length``
    (m,) [m], the ``base_pose`` (4, 4), the homogeneous ``tip_marker`` (4,) and the :func:`sigma_coefficients`."""
    spec, cc = model.spec, model.cc
    return {**active_set_maps(model), "radius": torch.tensor([s.radius for s in spec.segments], dtype=F64),
            "length": torch.tensor([s.length for s in spec.segments], dtype=F64),
            "base_pose": pose_from_parts(cc.base_rotation(), cc.base_translation),
            "tip_marker": torch.cat([cc.marker_offset(), torch.ones(1, dtype=F64)]),
            "sigma_coefficients": sigma_coefficients(model)}


def sigma_coefficients(model: HardwareModel) -> Tensor:
    """(σ₀ [m], c_ensemble, c_bend) float64 of σ = √(σ₀² + (c_ensemble·spread)² + (c_bend·‖ρ‖)²): the σ
    model of ``HardwareModel.predict`` (:meth:`~.checkpoint.HardwareModel.sigma_of`; absent terms 0).
    Raises ValueError for σ-model terms the exported module cannot compute (support distance, disagreement)."""
    sm = model.sigma_of()
    other = [t for t in sm.terms if t not in SIGMA_TERMS_EXPORTED]
    if other:
        raise ValueError(f"sigma_model: the exported FK computes the terms {SIGMA_TERMS_EXPORTED}, got "
                         f"{list(sm.terms)} (unsupported: {other}); save the model without them")
    coef = dict(zip(sm.terms, sm.coefficients.tolist(), strict=True))
    return torch.tensor([float(sm.floor), coef.get("ensemble", 0.0), coef.get("bend", 0.0)], dtype=F64)


class HardwareFK(nn.Module):
    """Servo commands (B, S) [mm] (+ play state (B, m, 2)) → (tip (B, 3) [m], tip_std (B, 3) [m] (+ state)).

    Its AOTInductor package has its products written inline and its concatenations pointwise, as the synthetic
    FK's (batch 1, 3 members, side by side: p50 79 → 47 µs, outputs within 4e-9 m)."""

    inline_products = True
    inductor_configs = {"force_pointwise_cat": True}

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        spec = model.spec
        self.history, self.num_segments, self.num_servos = model.history, spec.num_segments, len(model.servo_ids)
        with torch.no_grad():
            buffers = {**model_constants(model), "play_width": torch.tensor(model.play_width, dtype=F64),
                       **_stacked_members(model.members)}
            buffers["twist_directions"] = cc_twist_directions(buffers["radius"])
        for name, value in buffers.items():   # contiguous: torch.export.save stores whole tensors, not views
            self.register_buffer(name, value.detach().to(dtype).contiguous())
        self.ensemble = len(model.members)
        self.activation = activation_name([m.net for m in model.members])
        self.spec = spec

    def clarke(self, servo: Tensor, derivative: bool = True) -> tuple[Tensor, Tensor | None]:
        """ρ (B, m, 2) [m, nominal-radius convention] of the commands and ∂ρ/∂servo (B, m, 2, S) [m/mm]:
        the sign violations of all 2ᴺ active sets' solutions in one product, the least-violating set's
        affine map (:func:`~.slack.select_active_set`)."""
        n_sets = self.rho_gain.shape[0]
        # products as broadcast-multiply-sums, not BLAS calls: Inductor fuses them with the relu, the sums
        # and the argmin into a few loops (batch-1 AOTI runner of the v4 model's encoder 13.6 → 7.2 µs)
        violation = (servo.unsqueeze(-1) * self.violation_map).sum(-2) + self.violation_offset   # (B, 2ᴺ·N)
        best = violation.relu().unflatten(-1, (n_sets, -1)).sum(-1).argmin(-1)                 # (B,)
        gain = self.rho_gain[best]                                                             # (B, S, 2m)
        rho = (servo.unsqueeze(-1) * gain).sum(-2) + self.rho_offset[best].squeeze(-2)         # (B, 2m)
        rho = rho.reshape(-1, self.num_segments, 2)
        return rho, gain.mT.reshape(-1, self.num_segments, 2, self.num_servos) if derivative else None

    def initial_state(self, servo: Tensor) -> Tensor:
        """Play state to start a sequence at command ``servo`` (B, S): its own ρ (B, m, 2) [m]."""
        return self.clarke(servo, derivative=False)[0]

    def play(self, rho: Tensor, state: Tensor, derivative: bool = True) -> tuple[Tensor, Tensor, Tensor | None]:
        """One play-operator step: (memory (B, m, 2), new state, ∂memory/∂ρ (B, m, 2, 2) or None)."""
        diff = state - rho
        norm = torch.linalg.vector_norm(diff, dim=-1, keepdim=True).clamp_min(1e-30)
        inside = norm <= self.play_width
        new = torch.where(inside, state, torch.addcmul(rho, diff, self.play_width / norm))
        memory = (rho - new) / self.play_width
        if not derivative:
            return memory, new, None
        unit = diff / norm
        eye = torch.eye(2, dtype=rho.dtype)
        drag = (eye - unit.unsqueeze(-1) * unit.unsqueeze(-2)) / norm.unsqueeze(-1)
        return memory, new, torch.where(inside.unsqueeze(-1), eye / self.play_width, drag)

    def members(self, rho: Tensor, memory: Tensor | None, tangent: tuple[Tensor, Tensor | None] | None = None):
        """Corrected ρ' (B, K, m, 2) of every member and, given input tangents (∂ρ (B, m, 2, T), ∂memory or None), its
        tangents (B, K, m, 2, T) (else None): forward mode as stacked rows (:func:`~dacr_learn.folding.tangent_rows`),
        the first layers of all K members in one product, the further layers batched over the members (bmm)."""
        x = rho if memory is None else torch.cat([rho, memory], -1)                        # (B, m, I)
        rows = x.unsqueeze(2)                                                              # (B, m, 1, I)
        if tangent is not None:
            dx = tangent[0] if memory is None else torch.cat([tangent[0], tangent[1]], -2)  # (B, m, I, T)
            rows = torch.cat([rows, dx.transpose(-1, -2)], 2)                              # (B, m, 1 + T, I)
        (b, m, n, _), (k, h) = rows.shape, self.w_hidden.shape[:2]
        if n == 1:                                                                         # no tangents: views only
            a = (x @ self.first_all + self.b_first_all).view(b * m, k, h).transpose(0, 1).unsqueeze(2)
        else:                                                                              # the bias on the value row
            bias = self.b_first_all.unsqueeze(1) * (torch.arange(n) == 0).to(rho.dtype).unsqueeze(-1)
            a = (rows @ self.first_all + bias).view(b, m, n, k, h).permute(3, 0, 1, 2, 4).reshape(k, b * m, n, h)
        a = tangent_rows(a, [(self.w_hidden, self.b_hidden), (self.w_last, self.b_last)], self.activation)
        a = a.view(k, b, m, n, 2).transpose(0, 1)                                         # (B, K, m, 1 + T, 2)
        out = rho.unsqueeze(1) + a[:, :, :, 0]
        return out, None if tangent is None else tangent[0].unsqueeze(1) + a[:, :, :, 1:].transpose(-1, -2)

    def mean_std(self, tips: Tensor, rho: Tensor) -> tuple[Tensor, Tensor]:
        """Ensemble mean and σ = √(σ₀² + (c_e·spread)² + (c_b·‖ρ‖)²) (:func:`sigma_coefficients`) of tips
        (B, K, 3) [m] at commands of Clarke coordinates ρ (B, m, 2) [m]; one member has no spread."""
        floor, c_ens, c_bend = self.sigma_coefficients
        var = floor**2 + (c_bend * rho.flatten(-2).norm(dim=-1, keepdim=True)) ** 2          # (B, 1)
        if self.ensemble == 1:
            return tips[:, 0], var.sqrt().expand(-1, 3).contiguous()   # every axis; an output owns its memory
        return tips.mean(1), (var + (c_ens * tips.std(1, correction=1)) ** 2).sqrt()

    def forward(self, servo: Tensor, state: Tensor | None = None):
        rho, _ = self.clarke(servo, derivative=False)
        memory, new_state = None, None
        if self.history:
            memory, new_state, _ = self.play(rho, state, derivative=False)
        corrected = self.members(rho, memory)[0]                                        # (B, K, m, 2)
        tips = chained_marker_point(self.base_pose, cc_segment_poses(corrected, self.radius, self.length),
                                    self.tip_marker)                                    # (B, K, 3)
        tip, std = self.mean_std(tips, rho)
        return (tip, std, new_state) if self.history else (tip, std)


class HardwareJacobian(nn.Module):
    """Servo (B, S) [mm] (+ state) → (tip (B, 3) [m], J = ∂tip/∂servo (B, 3, S) [m/mm] (+ new state))."""

    def __init__(self, model: HardwareModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.fk = HardwareFK(model, dtype)

    def forward(self, servo: Tensor, state: Tensor | None = None):
        fk = self.fk
        rho, drho = fk.clarke(servo)                                          # (B, m, 2), (B, m, 2, S)
        memory, new_state, tangent = None, None, (drho, None)
        if fk.history:
            memory, new_state, dmem = fk.play(rho, state)
            tangent = (drho, dmem @ drho)
        corrected, dcorr = fk.members(rho, memory, tangent)                   # (B, K, m, 2), (B, K, m, 2, S)
        tips, dtip = cc_tip_and_jacobian(corrected, fk.radius, fk.length, fk.twist_directions, fk.base_pose,
                                         fk.tip_marker)                      # (B, K, 3), (B, K, m, 2, 3)
        b, k = corrected.shape[:2]                                            # J = mean over members of dtip · dcorr
        jac = dtip.reshape(b, -1, 3).mT @ dcorr.reshape(b, -1, dcorr.shape[-1]) / k
        tip = tips.mean(1)
        return (tip, jac, new_state) if fk.history else (tip, jac)


class InitialState(nn.Module):
    """servo (B, S) [mm] → play state (B, m, 2) [m] to start a sequence with (history models): the
    ``initial_state`` of an FK module (:class:`HardwareFK`, or the generated one), as a module to export."""

    def __init__(self, fk: nn.Module):
        super().__init__()
        self.fk = fk

    def forward(self, servo: Tensor) -> Tensor:
        return self.fk.initial_state(servo)


def active_set_maps(model: HardwareModel) -> dict[str, Tensor]:
    """The slack QP folded per active set S (:func:`~.slack.active_set_gains`, float64), x = servo·A + a₀ + p [m]:
    ``rho_gain`` (2ᴺ, S, 2m), ``rho_offset`` (2ᴺ, 1, 2m) give ρ_S·d_nominal/d_effective of servo [mm];
    ``violation_map`` (S, 2ᴺ·N), ``violation_offset`` the signed, weighted residuals of select_active_set."""
    spec, enc, s = model.spec, model.cc.encoder, len(model.servo_ids)
    a0 = model.smap.command_displacements(spec, model.servo_ids, torch.zeros(1, s, dtype=F64))[0]
    a = model.smap.command_displacements(spec, model.servo_ids, 1e-3 * torch.eye(s, dtype=F64)) - a0   # (S, N)
    a0 = a0 + enc.tendon_pretension()
    g, tendon_w = enc.displacement_map(), 1.0 / enc.path_length
    sets, gain = active_set_gains(g, enc.bend_weights(), tendon_w)                    # (2ᴺ, N), (2ᴺ, 2m, N)
    weight = torch.where(sets, -1.0, 1.0).to(F64) * tendon_w                          # (2ᴺ, N)
    keep = torch.eye(g.shape[0], dtype=F64) - g @ gain                                # x − Gρ_S = (I − G K_S) x
    scale = (enc.radius / enc.effective_radius()).repeat_interleave(2).unsqueeze(-1)
    return {"rho_gain": (scale * gain @ a.mT).mT.contiguous(), "rho_offset": ((scale * gain) @ a0).unsqueeze(-2),
            "violation_map": torch.einsum("sij,kj->ksi", keep, a).mul(weight).flatten(-2),
            "violation_offset": ((keep @ a0) * weight).flatten()}


def _stacked_members(members) -> dict[str, Tensor]:
    """Residual networks of the K members stacked (float64), weights (K, in, out): the first layers side by
    side as one (in, K·H) map of ρ [and memory] (input standardisation folded in) with the one-hot part folded
    into a per-segment bias (m, K·H); hidden and output layers (K, in, out), the output scale folded in."""
    nets = [linear_layers(m.net) for m in members]
    if any(len(n) != 3 for n in nets):
        raise ValueError(f"members: expected residual networks with 3 linear layers, got {[len(n) for n in nets]}")
    w1 = torch.stack([n[0].weight for n in nets]).to(F64)                  # (K, H, 2 [+2] + m)
    std = torch.stack([m.rho_std for m in members]).to(F64).reshape(-1, 1, 1)
    m = members[0].onehot.shape[0]
    hist = 2 if members[0].history else 0
    w_first = torch.cat([(w1[..., :2] / std).mT, w1[..., 2:2 + hist].mT], -2)   # (K, 2 [+2], H): ρ [and memory]
    b_first = torch.stack([n[0].bias for n in nets]).to(F64).unsqueeze(1) + w1[..., 2 + hist:].mT[:, :m]  # (K, m, H)
    w_hidden, b_hidden = stacked_linear([n[1] for n in nets])
    w_last, b_last = stacked_linear([n[2] for n in nets], RESIDUAL_RHO_SCALE)
    # the K first layers as one (the input is shared): hidden units of the members side by side
    return {"first_all": w_first.permute(1, 0, 2).flatten(1),              # (in, K·H)
            "b_first_all": b_first.permute(1, 0, 2).flatten(1),            # (m, K·H)
            "w_hidden": w_hidden, "b_hidden": b_hidden, "w_last": w_last, "b_last": b_last}
