"""Folded inference module of the compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`):
the Clarke front-end, the per-segment standardisation, the context and the first layer folded into one affine
map (as :mod:`dacr_learn.inference` does for the monolithic FK), then the shared MLP, the twist (or 6D) head
and the products of the segment transforms. Joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m]."""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import rotation_6d_to_matrix
from torch import Tensor, nn

from .compositional import HEADS
from .inference import ClarkeFold, FoldedMLP, linear_layers
from .lie import pose_from_parts, twist_exp
from .models import Standardizer, actuated_selection, actuated_to_features, fixed_features

__all__ = ["InferenceCompositionalFK", "compositional_first_layer"]

_F64 = torch.float64


class InferenceCompositionalFK(nn.Module):
    """Compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`) with the front-end
    folded in: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].

    Encoder, per-segment standardisation, context ("segment": a constant, "distal": a sum of
    standardised features) and the first layer together with the learned linear skip are affine in
    u = [q − q_ref, g], so one matrix gives every segment's pre-activations at once,
    (B, m·(W + O)); for type-III segments it acts on the exact features f instead (β = sqrt(h² − (αr)²)).
    The translation scale L_s is folded into the output rows. Then the shared MLP runs on (B, m, W),
    the head gives T_k and the products compose the tip.
    """

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.rotation, self.num_segments = model.rotation, model.spec.num_segments
        self.num_joints, self.features_mode = model.spec.num_joints, "clarke"
        self.width, self.out = linear_layers(model.net)[0].out_features, HEADS[model.rotation]
        self.fold = ClarkeFold(model.spec)
        scale = torch.ones(self.out, dtype=_F64)
        scale[:3] = model.length_scale.to(_F64)
        k, k0 = compositional_first_layer(model, scale)                        # acts on actuated features f
        self.on_features = self.fold.has_type3
        if not self.on_features:
            k, k0 = k @ self.fold.E, k0 + k @ self.fold.e0
        self.fold.to(dtype)
        self.mlp = FoldedMLP(model.net, (k, k0), scale, torch.zeros_like(scale), dtype)
        self.register_buffer("bottom", torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype))

    def segment_transforms(self, q: Tensor) -> Tensor:
        """T_k (B, m, 4, 4) of every segment."""
        u = self.fold.inputs(q)
        pre = self.mlp.first(self.fold.features(u) if self.on_features else u)
        pre = pre.unflatten(-1, (self.num_segments, self.width + self.out))
        out = self.mlp(pre[..., :self.width]) + pre[..., self.width:]
        if self.rotation == "twist":
            return twist_exp(out)
        return pose_from_parts(rotation_6d_to_matrix(out[..., 3:]), out[..., :3], self.bottom)

    def forward(self, q: Tensor) -> Tensor:
        t = self.segment_transforms(q)
        tip = t[:, 0]
        for k in range(1, self.num_segments):
            tip = tip @ t[:, k]
        return tip


def compositional_first_layer(model, scale: Tensor) -> tuple[Tensor, Tensor]:
    """(K, k₀) float64 with [a₁ | scale·skip] of every segment = K·f + k₀, f the actuated features (D,).

    Found by probing the (affine) map with unit vectors, through the model's own modules.
    """
    spec, front = model.spec, model.front
    sel, fixed = actuated_selection(spec).to(_F64), fixed_features(spec, _F64)
    first, skip = linear_layers(model.net)[0], model.skip
    w = torch.cat([first.weight, scale[:, None] * skip.weight]).detach().to(_F64)
    b = torch.cat([first.bias.detach().to(_F64), torch.zeros(skip.out_features, dtype=_F64)])
    norm = Standardizer(4).to(_F64)
    norm.load_state_dict({k: v.to(_F64) for k, v in front.norm.state_dict().items()})
    context = front.context_matrix.to(_F64)

    def affine(f: Tensor) -> Tensor:
        x = norm(actuated_to_features(f, sel, fixed))                    # (P, m, 4)
        if front.context == "segment":
            x = torch.cat([x, context.expand(x.shape[0], -1, -1)], dim=-1)
        elif front.context == "distal":
            x = torch.cat([x, context @ x], dim=-1)
        return (x @ w.mT + b).flatten(-2)                                 # (P, m·(W + O))

    d = sel.shape[0]
    probe = affine(torch.cat([torch.zeros(1, d, dtype=_F64), torch.eye(d, dtype=_F64)]))
    return (probe[1:] - probe[0]).mT.contiguous(), probe[0].clone()
