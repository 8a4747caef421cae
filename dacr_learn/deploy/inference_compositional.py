"""Folded inference modules of the compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`;
docs/compositional.md, "Export"): the Clarke front-end, the per-segment standardisation, the context and the first
layer folded into one affine map (as :mod:`dacr_learn.deploy.inference` does for the monolithic FK), then the shared
MLP, the twist (or 6D) head and the products of the segment transforms: :class:`InferenceCompositionalFK` (q (B, N)
→ tip pose (B, 4, 4) [m]) and, twist head only, :class:`InferenceCompositionalJacobian` (the outputs of
:class:`~dacr_learn.deploy.inference.InferenceJacobian`).

Both roll a twisting segment by its α first, T_k = Rz(α_k)·head (``CompositionalFK.roll``): α_k is a joint of the
vector, picked by ``roll_select`` (N, m)."""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import rotation_6d_to_matrix
from torch import Tensor, nn

from ..checks import F64
from ..clarke_space import ClarkeFold, feature_columns
from ..compositional import HEADS
from ..folding import affine_probe, linear_layers, tangent_rows
from ..lie import chain_products, pose_from_parts, roll_z, twist_chain_jacobian, twist_exp
from ..models import Standardizer, actuated_selection, actuated_to_features, fixed_features
from .inference import FoldedMLP

__all__ = ["InferenceCompositionalFK", "InferenceCompositionalJacobian", "compositional_first_layer", "output_scale"]


class InferenceCompositionalFK(nn.Module):
    """Compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`) with the front-end
    folded in: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].

    Encoder, feature units, per-segment standardisation, context and the first layer with the learned linear skip
    are affine in u = [q − q_ref, g] (for type-III segments: in the exact features f), so one matrix gives every
    segment's pre-activations (B, m·(W + O)); the outputs are scaled by each segment's translation unit
    (``out_scale``, (m, O)); then the shared MLP on (B, m, W), the head T_k and the products.
    """

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.rotation, self.num_segments = model.rotation, model.spec.num_segments
        self.num_joints, self.features_mode = model.spec.num_joints, "clarke"
        self.width, self.out = linear_layers(model.net)[0].out_features, HEADS[model.rotation]
        self.fold = ClarkeFold(model.spec)
        ones = torch.ones(self.out, dtype=F64)
        k, k0 = compositional_first_layer(model)                                # acts on actuated features f
        self.on_features = self.fold.has_type3
        if not self.on_features:
            k, k0 = k @ self.fold.E, k0 + k @ self.fold.e0
        self.fold.to(dtype)
        self.mlp = FoldedMLP(model.net, (k, k0), ones, torch.zeros_like(ones), dtype)
        self.register_buffer("out_scale", output_scale(model).to(dtype))
        self.register_buffer("bottom", torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype))
        self.rolls = bool(model.rolls)
        self.register_buffer("roll_select", roll_selection(model).to(dtype) if self.rolls else None)

    def segment_outputs(self, u: Tensor, seed: Tensor | None = None) -> Tensor:
        """Head inputs (B, m, 1, O) of every segment from the inputs u (B, N + n_g) (``fold.inputs``); with tangent
        rows ``seed`` (m, T, W + O) of the first layer, also their tangents: (B, m, 1 + T, O) (forward mode as
        stacked rows, :func:`~dacr_learn.folding.tangent_rows`)."""
        pre = self.mlp.first(self.fold.features(u) if self.on_features else u)
        rows = pre.unflatten(-1, (self.num_segments, self.width + self.out)).unsqueeze(-2)  # (B, m, 1, W + O)
        if seed is not None:
            rows = torch.cat([rows, seed.expand(rows.shape[0], -1, -1, -1)], dim=-2)       # (B, m, 1 + T, W + O)
        a = self.mlp(rows[..., :self.width]) if seed is None else \
            tangent_rows(rows[..., :self.width], self.mlp.layers(), self.mlp.act)
        return (a + rows[..., self.width:]) * self.out_scale.unsqueeze(-2)

    def segment_transforms(self, q: Tensor) -> Tensor:
        """T_k (B, m, 4, 4) of every segment."""
        out = self.segment_outputs(self.fold.inputs(q))[..., 0, :]
        alpha = q @ self.roll_select if self.rolls else None
        if self.rotation == "twist":
            return twist_exp(out, alpha)
        t = pose_from_parts(rotation_6d_to_matrix(out[..., 3:]), out[..., :3], self.bottom)
        return t if alpha is None else roll_z(t, alpha)

    def forward(self, q: Tensor) -> Tensor:
        return chain_products(self.segment_transforms(q), tip_only=True)


class InferenceCompositionalJacobian(nn.Module):
    """Compositional learned FK and its Jacobians: q (B, N) → (pose (B, 4, 4), J_f (B, 6, D), J_q (B, 6, N)).

    Rows of J: tip linear velocity [m] and angular velocity [rad] in the base frame per unit of actuated
    feature (J_f) or joint (J_q = J_f·∂f/∂q), as :class:`~dacr_learn.deploy.inference.InferenceJacobian`. Twist head
    only (``rotation="twist"``; a ValueError otherwise).

    Built for few operations (batch 1 in a control loop): forward mode as stacked rows (value and T tangent rows
    through each layer in one product, :func:`~dacr_learn.folding.tangent_rows`), T only the features segment k's
    first layer depends on (2 per type-I segment without context, not all D); the transforms, tangents, roll and
    chain by the kernel (:func:`~dacr_learn.lie.twist_chain_jacobian`); J_f and J_q in one product with a constant
    map [selection | selection·∂f/∂q] when ∂f/∂q is constant, else J_q = J_f·∂f/∂q(q).
    """

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        if model.rotation != "twist":
            raise ValueError("rotation: the compositional Jacobian module needs the 'twist' head, "
                             f"got {model.rotation!r}")
        fk = self.fk = InferenceCompositionalFK(model, dtype)
        m, w = fk.num_segments, fk.width + fk.out
        k = compositional_first_layer(model)[0]                             # acts on actuated features f
        d = self.num_features = k.shape[1]
        seed = k.view(m, w, d).mT                                           # ∂(pre-activations | skip)/∂f (m, D, W + O)
        used = [torch.nonzero(seed[j].abs().sum(-1) > 0).flatten().tolist() for j in range(m)]
        rolled = torch.nonzero(model.roll).flatten().tolist()
        rolled_alpha = list(zip(rolled, feature_columns(model.spec, "alpha", rolled), strict=True))  # (segment, α col)
        for j, col in rolled_alpha:
            if col not in used[j]:                                          # the roll depends on α in any case
                used[j].append(col)
        t = max(1, *map(len, used))
        local = torch.zeros(m, t, w, dtype=F64)                            # the T tangent rows of each segment
        pick = torch.zeros(m, t, d, dtype=F64)                             # (segment, row) → feature column
        roll_row = torch.zeros(m, t, 1, dtype=F64)                         # 1 on the α row of a rolled segment
        for j, cols in enumerate(used):
            local[j, :len(cols)] = seed[j, cols]
            pick[j, range(len(cols)), cols] = 1.0
        for j, col in rolled_alpha:
            roll_row[j, used[j].index(col)] = 1.0
        self.constant_dfdq = not (fk.fold.has_g or fk.fold.has_type3)
        pick = pick.flatten(0, 1)                                           # (m·T, D)
        if self.constant_dfdq:                                              # [J_f | J_q] in one product
            pick = torch.cat([pick, pick @ ClarkeFold(model.spec).E[:, :fk.num_joints]], dim=-1)
        self.register_buffer("seed", local.to(dtype))
        self.register_buffer("pick", pick.to(dtype))
        self.register_buffer("roll_row", roll_row.to(dtype) if fk.rolls else None)

    def forward(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        fk = self.fk
        u = fk.fold.inputs(q)
        xi = fk.segment_outputs(u, self.seed)                               # (B, m, 1 + T, 6)
        alpha = q @ fk.roll_select if fk.rolls else None                    # T_k = Rz(α_k)·exp(ξ_k^)
        pose, jac = twist_chain_jacobian(xi[..., 0, :], xi[..., 1:, :], alpha, self.roll_row)   # J (B, 6, m·T)
        jac = jac @ self.pick                                               # (B, 6, D [+ N])
        if self.constant_dfdq:
            return pose, jac[..., :self.num_features], jac[..., self.num_features:]
        return pose, jac, jac @ fk.fold.jacobian(q, u)


def roll_selection(model) -> Tensor:
    """(N, m) float64 picking each rolled segment's α (a twist joint) out of the joint vector; zero columns for
    the segments that are not rolled."""
    spec = model.spec                     # the twist joints, in segment order, are the joint vector's last entries
    twist = torch.eye(spec.num_segments, dtype=F64)[[k for k, s in enumerate(spec.segments) if s.twists]] * model.roll
    return torch.cat([torch.zeros(spec.num_length_joints, spec.num_segments, dtype=F64), twist])


def output_scale(model) -> Tensor:
    """(m, O) float64 factors of the network outputs: the segment's translation unit on the twist's (or
    position's) first three columns, ones elsewhere."""
    scale = torch.ones(model.spec.num_segments, HEADS[model.rotation], dtype=F64)
    scale[:, :3] = model.length_scale.to(F64).unsqueeze(-1)
    return scale


def compositional_first_layer(model) -> tuple[Tensor, Tensor]:
    """(K, k₀) float64 with [a₁ | skip] of every segment = K·f + k₀, f the actuated features (D,).

    Found by probing the (affine) map with unit vectors through the model's own modules
    (:func:`~dacr_learn.folding.affine_probe`).
    """
    spec, front = model.spec, model.front
    sel, fixed = actuated_selection(spec).to(F64), fixed_features(spec, F64)
    first, skip = linear_layers(model.net)[0], model.skip
    unit = front.unit.to(F64)
    w = torch.cat([first.weight, skip.weight]).detach().to(F64)
    b = torch.cat([first.bias.detach().to(F64), torch.zeros(skip.out_features, dtype=F64)])
    norm = Standardizer(4).to(F64)
    norm.load_state_dict({k: v.to(F64) for k, v in front.norm.state_dict().items()})

    def affine(f: Tensor) -> Tensor:
        x = norm(actuated_to_features(f, sel, fixed) / unit)             # (P, m, 4)
        return (front.with_context(x) @ w.mT + b).flatten(-2)            # (P, m·(W + O))

    k, k0 = affine_probe(affine, sel.shape[0])
    return k.mT.contiguous(), k0
