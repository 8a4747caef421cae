"""Folded inference modules of the compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`):
the Clarke front-end, the per-segment standardisation, the context and the first layer folded into one affine
map (as :mod:`dacr_learn.inference` does for the monolithic FK), then the shared MLP, the twist (or 6D) head
and the products of the segment transforms.

- :class:`InferenceCompositionalFK`: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].
- :class:`InferenceCompositionalJacobian` (twist head): joint vector (B, N) → (pose (B, 4, 4), J_f (B, 6, D),
  J_q (B, 6, N)), the same outputs as :class:`~dacr_learn.inference.InferenceJacobian`: the segment twists and
  their tangents along the D actuated features in forward mode through the MLP, the tangent of each segment's
  exponential (:func:`~dacr_learn.lie.twist_exp_and_tangent`), and the product rule over the chain
  (∂T_tip = Σ_k T_1⋯T_{k−1} · ∂T_k · T_{k+1}⋯T_m, prefix and suffix products)."""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import rotation_6d_to_matrix
from torch import Tensor, nn

from .compositional import HEADS
from .control import twist_jacobian
from .inference import ClarkeFold, FoldedMLP, linear_layers
from .lie import pose_from_parts, twist_exp, twist_exp_and_tangent
from .models import Standardizer, actuated_selection, actuated_to_features, fixed_features

__all__ = ["InferenceCompositionalFK", "InferenceCompositionalJacobian", "compositional_first_layer", "output_scale"]

_F64 = torch.float64


class InferenceCompositionalFK(nn.Module):
    """Compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`) with the front-end
    folded in: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].

    Encoder, per-segment standardisation, context ("segment": a constant, "distal": a sum of
    standardised features) and the first layer together with the learned linear skip are affine in
    u = [q − q_ref, g], so one matrix gives every segment's pre-activations at once,
    (B, m·(W + O)); for type-III segments it acts on the exact features f instead (β = sqrt(h² − (αr)²)).
    Feature units (ρ/d, β/l) are folded in; the outputs are scaled by each segment's translation unit
    (``out_scale``, (m, O)). Then the shared MLP runs on (B, m, W), the head gives T_k and the products
    compose the tip.
    """

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.rotation, self.num_segments = model.rotation, model.spec.num_segments
        self.num_joints, self.features_mode = model.spec.num_joints, "clarke"
        self.width, self.out = linear_layers(model.net)[0].out_features, HEADS[model.rotation]
        self.fold = ClarkeFold(model.spec)
        ones = torch.ones(self.out, dtype=_F64)
        k, k0 = compositional_first_layer(model)                                # acts on actuated features f
        self.on_features = self.fold.has_type3
        if not self.on_features:
            k, k0 = k @ self.fold.E, k0 + k @ self.fold.e0
        self.fold.to(dtype)
        self.mlp = FoldedMLP(model.net, (k, k0), ones, torch.zeros_like(ones), dtype)
        self.register_buffer("out_scale", output_scale(model).to(dtype))
        self.register_buffer("bottom", torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype))

    def segment_transforms(self, q: Tensor) -> Tensor:
        """T_k (B, m, 4, 4) of every segment."""
        u = self.fold.inputs(q)
        pre = self.mlp.first(self.fold.features(u) if self.on_features else u)
        pre = pre.unflatten(-1, (self.num_segments, self.width + self.out))
        out = (self.mlp(pre[..., :self.width]) + pre[..., self.width:]) * self.out_scale
        if self.rotation == "twist":
            return twist_exp(out)
        return pose_from_parts(rotation_6d_to_matrix(out[..., 3:]), out[..., :3], self.bottom)

    def forward(self, q: Tensor) -> Tensor:
        t = self.segment_transforms(q)
        tip = t[:, 0]
        for k in range(1, self.num_segments):
            tip = tip @ t[:, k]
        return tip


class InferenceCompositionalJacobian(nn.Module):
    """Compositional learned FK and its Jacobians: q (B, N) → (pose (B, 4, 4), J_f (B, 6, D), J_q (B, 6, N)).

    Rows of J: tip linear velocity [m] and angular velocity [rad] in the base frame per unit of actuated
    feature (J_f) or joint (J_q = J_f·∂f/∂q), as :class:`~dacr_learn.inference.InferenceJacobian`. Twist head
    only (``rotation="twist"``; a ValueError otherwise)."""

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        if model.rotation != "twist":
            raise ValueError("rotation: the compositional Jacobian module needs the 'twist' head, "
                             f"got {model.rotation!r}")
        self.num_segments, self.num_joints = model.spec.num_segments, model.spec.num_joints
        self.width, self.out = linear_layers(model.net)[0].out_features, HEADS[model.rotation]
        self.fold = ClarkeFold(model.spec)
        ones = torch.ones(self.out, dtype=_F64)
        k, k0 = compositional_first_layer(model)                          # acts on actuated features f
        d = k.shape[1]
        # ∂(pre-activations | skip part) / ∂f per segment: (m, D, W + O), the tangents the MLP carries forward
        self.register_buffer("seed", k.view(self.num_segments, self.width + self.out, d).mT.contiguous().to(dtype))
        self.fold.to(dtype)
        self.mlp = FoldedMLP(model.net, (k, k0), ones, torch.zeros_like(ones), dtype)
        self.register_buffer("out_scale", output_scale(model).to(dtype))
        self.register_buffer("eye", torch.eye(4, dtype=dtype))

    def forward(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        u = self.fold.inputs(q)
        f = self.fold.features(u)
        pre = self.mlp.first(f).unflatten(-1, (self.num_segments, self.width + self.out))      # (B, m, W + O)
        seed = self.seed.expand(q.shape[0], -1, -1, -1)                                         # (B, m, D, W + O)
        out, dout = self.mlp.forward_with_tangents(pre[..., :self.width], seed[..., :self.width])
        scale = self.out_scale.unsqueeze(-2)                                                    # (m, 1, 6)
        xi = (out + pre[..., self.width:]) * self.out_scale                                      # (B, m, 6)
        dxi = (dout + seed[..., self.width:]) * scale                                            # (B, m, D, 6)
        t, dt = twist_exp_and_tangent(xi, dxi)                                        # (B, m, 4, 4), (B, m, D, 4, 4)
        m = self.num_segments
        prefix, suffix = [self.eye.expand(q.shape[0], 4, 4)], [self.eye.expand(q.shape[0], 4, 4)]
        for k in range(m):                                                  # T_1⋯T_k and T_{m−k}⋯T_m
            prefix.append(prefix[-1] @ t[:, k])
            suffix.append(t[:, m - 1 - k] @ suffix[-1])
        dpose = sum(prefix[k].unsqueeze(1) @ dt[:, k] @ suffix[m - 1 - k].unsqueeze(1) for k in range(m))
        pose = prefix[m]
        jac_f = twist_jacobian(pose, dpose.permute(0, 2, 3, 1))                                  # (B, 6, D)
        return pose, jac_f, jac_f @ self.fold.jacobian(q, u)


def output_scale(model) -> Tensor:
    """(m, O) float64 factors of the network outputs: the segment's translation unit on the twist's (or
    position's) first three columns, ones elsewhere."""
    scale = torch.ones(model.spec.num_segments, HEADS[model.rotation], dtype=_F64)
    scale[:, :3] = model.length_scale.to(_F64).unsqueeze(-1)
    return scale


def compositional_first_layer(model) -> tuple[Tensor, Tensor]:
    """(K, k₀) float64 with [a₁ | skip] of every segment = K·f + k₀, f the actuated features (D,).

    Found by probing the (affine) map with unit vectors, through the model's own modules.
    """
    spec, front = model.spec, model.front
    sel, fixed = actuated_selection(spec).to(_F64), fixed_features(spec, _F64)
    first, skip = linear_layers(model.net)[0], model.skip
    unit = front.unit.to(_F64)
    w = torch.cat([first.weight, skip.weight]).detach().to(_F64)
    b = torch.cat([first.bias.detach().to(_F64), torch.zeros(skip.out_features, dtype=_F64)])
    norm = Standardizer(4).to(_F64)
    norm.load_state_dict({k: v.to(_F64) for k, v in front.norm.state_dict().items()})
    context = front.context_matrix.to(_F64)

    def affine(f: Tensor) -> Tensor:
        x = norm(actuated_to_features(f, sel, fixed) / unit)             # (P, m, 4)
        if front.context == "segment":
            x = torch.cat([x, context.expand(x.shape[0], -1, -1)], dim=-1)
        elif front.context == "distal":
            x = torch.cat([x, context @ x], dim=-1)
        return (x @ w.mT + b).flatten(-2)                                 # (P, m·(W + O))

    d = sel.shape[0]
    probe = affine(torch.cat([torch.zeros(1, d, dtype=_F64), torch.eye(d, dtype=_F64)]))
    return (probe[1:] - probe[0]).mT.contiguous(), probe[0].clone()
