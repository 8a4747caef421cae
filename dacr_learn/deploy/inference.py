"""Inference modules for controllers: learned FK, its Jacobian and learned IK as plain nn.Modules.

Built from a trained :class:`~dacr_learn.models.FKModel` / :class:`~dacr_learn.models.IKModel`
(no Lightning at run time). SI units throughout; inputs carry one batch dim:

- :class:`InferenceFK`: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].
- :class:`InferenceJacobian`: joint vector (B, N) → (pose (B, 4, 4), J_f (B, 6, D), J_q (B, 6, N)):
  the Jacobian of the tip twist (v_x, v_y, v_z [m], ω_x, ω_y, ω_z [rad], base frame, v of the
  tip point) w.r.t. the D actuated Clarke features (ρ_re, ρ_im per segment, β, α where actuated,
  in ``models.actuated_selection`` order) and w.r.t. the joint vector. J_f is the derivative of
  f ↦ FK(dec(f)), J_q of q ↦ FK(q); on the displacement constraint J_q = J_f·∂enc/∂q.
- :class:`InferenceIK`: tip pose (B, 4, 4) → joint vector (B, N); for "clarke" models through the
  Clarke decoder, so every output satisfies the displacement constraint.

What is folded into the first layer a₁ = K·u + k₀ and the last (in float64): docs/export.md, "What is folded".
"""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import quaternion_to_matrix, rotation_6d_to_matrix
from torch import Tensor, nn

from ..checks import F64
from ..clarke_space import ClarkeFold, DecoderJacobian
from ..folding import activation_name, linear_layers, tangent_rows
from ..layers import ClarkeDecoder
from ..lie import pose_from_parts
from ..models import FKModel, IKModel, actuated_to_features

# AOTInductor options of the Jacobian's package: matrix products as C++ GEMM kernels generated at export (no BLAS
# call; "CPP" alone: no timing of alternatives, so the same package on a loaded machine), concatenations pointwise.
# The last two keep Inductor from writing its table of choices to stderr.
GEMM_KERNELS = {"max_autotune": True, "max_autotune_gemm_backends": "CPP", "force_pointwise_cat": True,
                "autotune_num_choices_displayed": 0, "max_autotune_report_choices_stats": False}


def _frozen_linear(weight: Tensor, bias: Tensor, dtype: torch.dtype) -> nn.Linear:
    layer = nn.Linear(weight.shape[1], weight.shape[0], dtype=dtype)
    layer.weight.data.copy_(weight)
    layer.bias.data.copy_(bias)
    return layer.requires_grad_(False)


class FoldedMLP(nn.Module):
    """The MLP after the (folded) first affine map: hidden layers and a (scaled) output layer."""

    def __init__(self, net: nn.Sequential, first: tuple[Tensor, Tensor], out_scale: Tensor,
                 out_shift: Tensor, dtype: torch.dtype):
        super().__init__()
        self.act = activation_name(net)
        self.activation = next(m for m in net if not isinstance(m, nn.Linear))   # the model's own module
        lin = linear_layers(net)
        last = lin[-1]
        w_last = out_scale[:, None] * last.weight.detach().to(F64)
        b_last = out_scale * last.bias.detach().to(F64) + out_shift
        self.first = _frozen_linear(*first, dtype)
        self.hidden = nn.ModuleList(_frozen_linear(m.weight.detach(), m.bias.detach(), dtype) for m in lin[1:-1])
        self.last = _frozen_linear(w_last, b_last, dtype)

    def forward(self, a: Tensor) -> Tensor:
        """First-layer pre-activations (B, W) → network output (B, out): the frozen layers as they are (the
        fewest operations, for the FK's export program; :meth:`forward_with_tangents` for the tangents)."""
        for layer in self.hidden:
            a = layer(self.activation(a))
        return self.last(self.activation(a))

    def forward_with_tangents(self, a: Tensor, tangent: Tensor, weights: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Forward-mode derivative: pre-activations (B, W) with tangents (k, W) → (out (B, out), dout (B, k, out))
        (:func:`~dacr_learn.folding.tangent_rows`: value and tangents stacked, one product per layer). ``weights``:
        the hidden and output layers' weights as contiguous (in, out) matrices (:class:`InferenceJacobian` keeps
        them), the form Inductor's generated GEMM kernels take."""
        rows = torch.cat([a.unsqueeze(-2), tangent.expand(a.shape[0], -1, -1)], dim=-2)
        layers = [(w, layer.bias) for w, layer in zip(weights, [*self.hidden, self.last], strict=True)]
        rows = tangent_rows(rows, layers, self.act)
        return rows[..., 0, :], rows[..., 1:, :]

    def layers(self) -> list[tuple[Tensor, Tensor]]:
        """(weight (in, out), bias (out,)) of the hidden and output layers, for
        :func:`~dacr_learn.folding.tangent_rows`."""
        return [(layer.weight.mT, layer.bias) for layer in [*self.hidden, self.last]]


def _first_layer(net: nn.Sequential, mean: Tensor, std: Tensor) -> tuple[Tensor, Tensor]:
    """(W₁/std, b₁ − W₁·mean/std) in float64: the first layer acting on unstandardised inputs."""
    first = linear_layers(net)[0]
    w = first.weight.detach().to(F64) / std.to(F64)
    return w, first.bias.detach().to(F64) - w @ mean.to(F64)


def _rotation_tangent_6d(d6: Tensor, dd6: Tensor) -> tuple[Tensor, Tensor]:
    """Gram–Schmidt of the 6D rotation with tangents: (B, 6), (B, k, 6) → R (B, 3, 3), ω (B, k, 3).

    R has rows b₁, b₂, b₃ (as pytorch_kinematics' rotation_6d_to_matrix); ω = vee(dR·Rᵀ) in the base frame.
    """
    a1, a2, da1, da2 = d6[:, :3], d6[:, 3:], dd6[..., :3], dd6[..., 3:]
    n1 = torch.linalg.vector_norm(a1, dim=-1, keepdim=True).clamp_min(1e-12)
    b1 = a1 / n1
    db1 = (da1 - b1.unsqueeze(1) * (b1.unsqueeze(1) * da1).sum(-1, keepdim=True)) / n1.unsqueeze(1)
    c = (b1 * a2).sum(-1, keepdim=True)
    dc = (db1 * a2.unsqueeze(1)).sum(-1, keepdim=True) + (b1.unsqueeze(1) * da2).sum(-1, keepdim=True)
    e = a2 - c * b1
    de = da2 - dc * b1.unsqueeze(1) - c.unsqueeze(1) * db1
    n2 = torch.linalg.vector_norm(e, dim=-1, keepdim=True).clamp_min(1e-12)
    b2 = e / n2
    db2 = (de - b2.unsqueeze(1) * (b2.unsqueeze(1) * de).sum(-1, keepdim=True)) / n2.unsqueeze(1)
    b3 = torch.cross(b1, b2, dim=-1)
    db3 = (torch.cross(db1, b2.unsqueeze(1).expand_as(db1), dim=-1)
           + torch.cross(b1.unsqueeze(1).expand_as(db2), db2, dim=-1))
    omega = torch.stack([(db3 * b2.unsqueeze(1)).sum(-1), (db1 * b3.unsqueeze(1)).sum(-1),
                         (db2 * b1.unsqueeze(1)).sum(-1)], dim=-1)
    return torch.stack([b1, b2, b3], dim=-2), omega


def _rotation_tangent_quaternion(quat: Tensor, dquat: Tensor) -> tuple[Tensor, Tensor]:
    """Quaternion (w, x, y, z) with tangents: (B, 4), (B, k, 4) → R (B, 3, 3), ω (B, k, 3) [base frame].

    With q̂ = q/‖q‖ = (w, v): ω = 2(w·dv − dw·v + v × dv).
    """
    n = torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
    unit = quat / n
    dunit = (dquat - unit.unsqueeze(1) * (unit.unsqueeze(1) * dquat).sum(-1, keepdim=True)) / n.unsqueeze(1)
    w, v, dw, dv = unit[:, None, :1], unit[:, None, 1:], dunit[..., :1], dunit[..., 1:]
    omega = 2 * (w * dv - dw * v + torch.cross(v.expand_as(dv), dv, dim=-1))
    return quaternion_to_matrix(quat), omega


class InferenceFK(nn.Module):
    """Learned FK with the front-end folded in: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].

    Its AOTInductor package (:func:`~dacr_learn.deploy.export.write_module`) has the products of its one row per
    sample written inline and its concatenations pointwise: one generated kernel, no BLAS call (C++, batch 1, side
    by side: 3.5× faster, 96 → 42 ``operator new`` per call; docs/cpp.md)."""

    inline_products = True
    inductor_configs = {"force_pointwise_cat": True}

    def __init__(self, model: FKModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.rotation, self.features_mode = model.rotation, model.front.mode
        self.num_joints = model.spec.num_joints
        net, norm = model.net, model.front.norm
        w, b = _first_layer(net, norm.mean, norm.std)                     # acts on raw features x
        self.fold = ClarkeFold(model.spec) if self.features_mode == "clarke" else None
        if self.fold is not None:                                         # x = E·u + e₀
            k, k0 = w @ self.fold.E, b + w @ self.fold.e0
            k3 = w[:, self.fold.beta3].to(dtype) if self.fold.has_type3 else None
            self.register_buffer("k3", k3)                                # type III: β − h correction
            self.fold.to(dtype)
        else:                                                             # x = q = u + q_ref
            q_ref = ClarkeFold(model.spec).q_ref
            k, k0 = w, b + w @ q_ref
            self.register_buffer("q_ref", q_ref.to(dtype))
        self.register_buffer("seed", w.mT.contiguous().to(dtype))       # ∂a₁/∂x, (k, W)
        self.register_buffer("bottom", torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype))
        scale = torch.ones(net[-1].out_features, dtype=F64)
        scale[:3] = model.length                                          # position × total length
        self.mlp = FoldedMLP(net, (k, k0), scale, torch.zeros_like(scale), dtype)

    def inputs(self, q: Tensor) -> Tensor:
        return q - self.q_ref if self.fold is None else self.fold.inputs(q)

    def first_layer(self, u: Tensor) -> Tensor:
        """a₁ = K·u + k₀ (+ K₃·(β − h) for type III): (B, N + n_g) → (B, W)."""
        a = self.mlp.first(u)
        if self.fold is not None and self.fold.has_type3:
            h, _, beta = self.fold.type3_beta(u)
            a = a + (beta - h) @ self.k3.mT
        return a

    def pose(self, out: Tensor) -> Tensor:
        rot = (rotation_6d_to_matrix if self.rotation == "6d" else quaternion_to_matrix)(out[:, 3:])
        return pose_from_parts(rot, out[:, :3], self.bottom)

    def forward(self, q: Tensor) -> Tensor:
        return self.pose(self.mlp(self.first_layer(self.inputs(q))))


class InferenceJacobian(nn.Module):
    """Learned FK and its Jacobians: q (B, N) → (pose (B, 4, 4), J_f (B, 6, D), J_q (B, 6, N)).

    Rows of J: tip linear velocity [m] and angular velocity [rad] in the base frame, per unit of
    feature or joint (see the module docstring); computed in forward mode through the MLP.

    Its AOTInductor package has its products as C++ GEMM kernels generated at export (Inductor's CPP template,
    :data:`GEMM_KERNELS`) and its concatenations pointwise: no BLAS call and fewer buffers, each of which the
    runtime wraps in heap-allocated tensor handles per call (C++, batch 1, side by side: 1.6× faster, 218 → 121
    ``operator new`` per call; docs/cpp.md).
    """

    inductor_configs = GEMM_KERNELS

    def __init__(self, model: FKModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.fk = InferenceFK(model, dtype)
        self.fold = self.fk.fold if self.fk.fold is not None else ClarkeFold(model.spec).to(dtype)
        self.decoder_jacobian = DecoderJacobian(model.spec).to(dtype) if self.fk.fold is None else None
        mlp = self.fk.mlp
        for i, layer in enumerate([*mlp.hidden, mlp.last]):                # (in, out), contiguous
            self.register_buffer(f"weight{i}", layer.weight.detach().mT.contiguous())
        self.layers = len(mlp.hidden) + 1
        fold = self.fk.fold
        constant = fold is not None and not fold.has_g and not fold.has_type3
        self.register_buffer("feature_jacobian", fold.E[:, :fold.num_joints].contiguous() if constant else None)

    def forward(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        fk = self.fk
        u = fk.inputs(q)
        weights = [getattr(self, f"weight{i}") for i in range(self.layers)]
        out, dout = fk.mlp.forward_with_tangents(fk.first_layer(u), fk.seed, weights)
        if fk.rotation == "6d":
            rot, omega = _rotation_tangent_6d(out[:, 3:], dout[..., 3:])
        else:
            rot, omega = _rotation_tangent_quaternion(out[:, 3:], dout[..., 3:])
        jac = torch.cat([dout[..., :3], omega], dim=-1).mT                # (B, 6, k)
        pose = pose_from_parts(rot, out[:, :3], fk.bottom)
        if self.feature_jacobian is not None:                 # clarke, ∂f/∂q constant: k = D; one 2-D product
            return pose, jac, (jac.reshape(-1, jac.shape[-1]) @ self.feature_jacobian).view(q.shape[0], 6, -1)
        if self.decoder_jacobian is None:                                 # clarke: k = D
            return pose, jac, jac @ self.fold.jacobian(q, u)
        features = self.fold.features(self.fold.inputs(q))                # raw: k = N
        return pose, jac @ self.decoder_jacobian(features), jac


class InferenceIK(nn.Module):
    """Learned IK with the normalisations folded in: tip pose (B, 4, 4) [m] → joint vector (B, N)."""

    def __init__(self, model: IKModel, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.features_mode, self.num_joints = model.features, model.spec.num_joints
        scale = torch.ones(9, dtype=F64)
        scale[:3] = 1 / model.length                                      # v = [p / L, first two rows of R]
        w, b = _first_layer(model.net, model.in_norm.mean, model.in_norm.std)
        out_std, out_mean = model.out_norm.std.to(F64), model.out_norm.mean.to(F64)
        self.mlp = FoldedMLP(model.net, (w * scale, b), out_std, out_mean, dtype)
        if self.features_mode == "clarke":
            self.register_buffer("selection", model.selection.to(dtype))
            self.register_buffer("base", model.base_features.to(dtype))
            self.decoder = ClarkeDecoder(model.spec).to(dtype)

    def forward(self, pose: Tensor) -> Tensor:
        v = torch.cat([pose[:, :3, 3], pose[:, :2, :3].flatten(1)], dim=-1)
        y = self.mlp(self.mlp.first(v))
        if self.features_mode == "raw":
            return y
        return self.decoder(actuated_to_features(y, self.selection, self.base))
