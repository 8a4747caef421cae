"""Folded inference modules of the compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`):
the Clarke front-end, the per-segment standardisation, the context and the first layer folded into one affine
map (as :mod:`dacr_learn.deploy.inference` does for the monolithic FK), then the shared MLP, the twist (or 6D) head
and the products of the segment transforms.

- :class:`InferenceCompositionalFK`: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].
- :class:`InferenceCompositionalJacobian` (twist head): joint vector (B, N) → (pose (B, 4, 4), J_f (B, 6, D),
  J_q (B, 6, N)), the same outputs as :class:`~dacr_learn.deploy.inference.InferenceJacobian`: the segment twists and
  their tangents along the actuated features each segment depends on, in forward mode through the MLP (value
  and tangent rows stacked), then in closed form each segment's spatial velocity and its effect on the tip
  through the prefix rotations and suffix positions of the chain (no 4 × 4 tangent products).

Both roll a twisting segment by its α first, T_k = Rz(α_k)·head (``CompositionalFK.roll``): α_k is a joint of the
vector, picked by ``roll_select`` (N, m)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from pytorch_kinematics.transforms import rotation_6d_to_matrix
from torch import Tensor, nn

from ..clarke_space import ClarkeFold, feature_columns
from ..compositional import HEADS
from ..lie import exp_coefficients_and_derivatives, hat, pose_from_parts, roll_z, twist_exp
from ..models import Standardizer, actuated_selection, actuated_to_features, fixed_features
from .inference import FoldedMLP, activation_and_derivative, linear_layers

__all__ = ["InferenceCompositionalFK", "InferenceCompositionalJacobian", "compositional_first_layer", "output_scale"]

_F64 = torch.float64


class InferenceCompositionalFK(nn.Module):
    """Compositional learned FK (:class:`~dacr_learn.compositional.CompositionalFK`) with the front-end
    folded in: joint vector (B, N) [m, rad] → tip pose (B, 4, 4) [m].

    Encoder, per-segment standardisation, context (front.with_context: "segment" a constant, "distal" a
    sum of standardised features, "full" both kinds) and the first layer together with the learned
    linear skip are affine in
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
        self.rolls = bool(model.rolls)
        self.register_buffer("roll_select", roll_selection(model).to(dtype) if self.rolls else None)

    def segment_transforms(self, q: Tensor) -> Tensor:
        """T_k (B, m, 4, 4) of every segment."""
        u = self.fold.inputs(q)
        pre = self.mlp.first(self.fold.features(u) if self.on_features else u)
        pre = pre.unflatten(-1, (self.num_segments, self.width + self.out))
        out = (self.mlp(pre[..., :self.width]) + pre[..., self.width:]) * self.out_scale
        if self.rotation == "twist":
            t = twist_exp(out)
        else:
            t = pose_from_parts(rotation_6d_to_matrix(out[..., 3:]), out[..., :3], self.bottom)
        return roll_z(t, q @ self.roll_select) if self.rolls else t

    def forward(self, q: Tensor) -> Tensor:
        t = self.segment_transforms(q)
        tip = t[:, 0]
        for k in range(1, self.num_segments):
            tip = tip @ t[:, k]
        return tip


class InferenceCompositionalJacobian(nn.Module):
    """Compositional learned FK and its Jacobians: q (B, N) → (pose (B, 4, 4), J_f (B, 6, D), J_q (B, 6, N)).

    Rows of J: tip linear velocity [m] and angular velocity [rad] in the base frame per unit of actuated
    feature (J_f) or joint (J_q = J_f·∂f/∂q), as :class:`~dacr_learn.deploy.inference.InferenceJacobian`. Twist head
    only (``rotation="twist"``; a ValueError otherwise).

    Built for few operations (the control-loop case, batch 1):

    - Forward mode as stacked rows: per segment the value row and its T tangent rows go through each layer
      in one product, (B, m, 1 + T, W) (the bias on the value row only; the tangent rows scaled by σ' of the
      value). T counts only the features segment k's first layer depends on (``columns`` (m, T), padded with
      zero seeds): 2 per type-I segment without context, instead of all D.
    - The segment transforms and everything after them are pointwise: R_k = I + s·ω^ + f·ω^², with ω^² =
      ωωᵀ − φ²I; the spatial angular velocity of R_k along a tangent is b = J_l(ω)·dω = dω + f·ω×dω +
      g·ω×(ω×dω) (the left Jacobian of SO(3)), and a change of segment k moves the tip point by
      R_{P_{k−1}}·(dp_k + b × R_k·s_{k+1}), where R_{P_{k−1}} = R_1⋯R_{k−1} is the prefix rotation and s_{k+1}
      the tip's position in frame k (the suffix T_{k+1}⋯T_m applied to the origin); the angular rows are
      R_{P_{k−1}}·b. No 4 × 4 products and no tangent of the full transform.
    - The per-segment columns (B, 6, m·T) become J_f and J_q in one product with a constant map
      [selection | selection·∂f/∂q] when ∂f/∂q is constant (no twisting segment); otherwise J_q =
      J_f·∂f/∂q(q).
    """

    def __init__(self, model, dtype: torch.dtype = torch.float32):
        super().__init__()
        if model.rotation != "twist":
            raise ValueError("rotation: the compositional Jacobian module needs the 'twist' head, "
                             f"got {model.rotation!r}")
        m = self.num_segments = model.spec.num_segments
        self.num_joints = model.spec.num_joints
        self.width, self.out = linear_layers(model.net)[0].out_features, HEADS[model.rotation]
        self.fold = ClarkeFold(model.spec)
        ones = torch.ones(self.out, dtype=_F64)
        k, k0 = compositional_first_layer(model)                          # acts on actuated features f
        d = self.num_features = k.shape[1]
        seed = k.view(m, self.width + self.out, d).mT                     # ∂(pre-activations | skip)/∂f (m, D, W + O)
        used = [torch.nonzero(seed[j].abs().sum(-1) > 0).flatten().tolist() for j in range(m)]
        self.rolls = bool(model.rolls)
        rolled = torch.nonzero(model.roll).flatten().tolist()
        rolled_alpha = list(zip(rolled, feature_columns(model.spec, "alpha", rolled), strict=True))  # (segment, α col)
        for j, col in rolled_alpha:
            if col not in used[j]:                                          # the roll depends on α in any case
                used[j].append(col)
        t = max(1, *map(len, used))
        local = torch.zeros(m, t, self.width + self.out, dtype=_F64)      # the T tangent rows of each segment
        pick = torch.zeros(m, t, d, dtype=_F64)                           # (segment, row) → feature column
        for j, cols in enumerate(used):
            local[j, :len(cols)] = seed[j, cols]
            pick[j, range(len(cols)), cols] = 1.0
        self.on_features = self.fold.has_type3
        if not self.on_features:
            k, k0 = k @ self.fold.E, k0 + k @ self.fold.e0
        self.constant_dfdq = not (self.fold.has_g or self.fold.has_type3)
        pick = pick.flatten(0, 1)                                          # (m·T, D)
        if self.constant_dfdq:                                             # [J_f | J_q] in one product
            pick = torch.cat([pick, pick @ self.fold.E[:, :self.num_joints]], dim=-1)
        self.register_buffer("seed", local.to(dtype))
        self.register_buffer("pick", pick.to(dtype))
        self.register_buffer("value_row", (torch.arange(1 + t) == 0).to(dtype).unsqueeze(-1))   # (1 + T, 1)
        roll_row = torch.zeros(m, t, 1, dtype=_F64)                        # 1 on the α row of a rolled segment
        for j, col in rolled_alpha:
            roll_row[j, used[j].index(col)] = 1.0
        self.register_buffer("roll_row", roll_row.to(dtype) if self.rolls else None)
        self.register_buffer("roll_select", roll_selection(model).to(dtype) if self.rolls else None)
        self.fold.to(dtype)
        self.mlp = FoldedMLP(model.net, (k, k0), ones, torch.zeros_like(ones), dtype)
        self.register_buffer("out_scale", output_scale(model).to(dtype))
        self.register_buffer("bottom", torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype))

    def segment_twists(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Twists ξ_k (B, m, 6) and their tangents (B, m, T, 6) along each segment's tangent rows."""
        pre = self.mlp.first(self.fold.features(u) if self.on_features else u)
        pre = pre.unflatten(-1, (self.num_segments, self.width + self.out)).unsqueeze(-2)   # (B, m, 1, W + O)
        rows = torch.cat([pre, self.seed.expand(pre.shape[0], -1, -1, -1)], dim=-2)      # (B, m, 1 + T, W + O)
        a, mask = rows[..., :self.width], self.value_row
        for layer in [*self.mlp.hidden, self.mlp.last]:
            v = a[..., :1, :]
            s, ds = activation_and_derivative(self.mlp.act, v)
            a = F.linear(torch.cat([s, a[..., 1:, :] * ds], dim=-2), layer.weight) + layer.bias * mask
        xi = (a + rows[..., self.width:]) * self.out_scale.unsqueeze(-2)                  # (B, m, 1 + T, 6)
        return xi[..., 0, :], xi[..., 1:, :]

    def forward(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        u = self.fold.inputs(q)
        xi, dxi = self.segment_twists(u)
        rot, pos, ang, lin = _exp_and_spatial_tangents(xi, dxi)
        if self.rolls:                                                      # Rz(α)·exp(ξ) and its tangents
            rot, pos, ang, lin = _rolled(q @ self.roll_select, self.roll_row, rot, pos, ang, lin)
        # chain: prefix rotations R_1⋯R_{k−1} and tip positions s_{k+1} in frame k, k = 1 … m
        m = self.num_segments
        prefix, suffix = [None], [None]
        for j in range(1, m):
            prefix.append(rot[:, 0] if j == 1 else _mat3(prefix[-1], rot[:, j - 1]))
            suffix.append(pos[:, m - 1] if j == 1 else _matvec3(rot[:, m - j], suffix[-1]) + pos[:, m - j])
        tip_rot = rot[:, 0] if m == 1 else _mat3(prefix[-1], rot[:, m - 1])
        tip_pos = pos[:, 0] if m == 1 else _matvec3(rot[:, 0], suffix[-1]) + pos[:, 0]
        cols = []
        for j in range(m):
            rest = suffix[m - 1 - j]                                      # s_{j+2}: the tip in frame j + 1
            lin_j = lin[:, j] if rest is None else lin[:, j] + torch.linalg.cross(
                ang[:, j], _matvec3(rot[:, j], rest).unsqueeze(-2))
            both = torch.cat([lin_j, ang[:, j]], dim=-1)                  # (B, T, 6) in frame j
            cols.append((both if prefix[j] is None else _rotate_pairs(prefix[j], both)).mT)
        jac = (torch.cat(cols, dim=-1).flatten(0, 1) @ self.pick).view(q.shape[0], 6, -1)   # (B, 6, D [+ N])
        pose = torch.cat([torch.cat([tip_rot, tip_pos.unsqueeze(-1)], dim=-1),
                          self.bottom.expand(q.shape[0], 1, 4)], dim=-2)
        if self.constant_dfdq:
            return pose, jac[..., :self.num_features], jac[..., self.num_features:]
        return pose, jac, jac @ self.fold.jacobian(q, u)


def _rolled(alpha: Tensor, roll_row: Tensor, rot: Tensor, pos: Tensor, ang: Tensor, lin: Tensor):
    """R, p (B, m, 3[, 3]) and the spatial tangents b, dp (B, m, T, 3) of exp(ξ_k), rolled to those of
    Rz(α_k)·exp(ξ_k): every vector rotated by Rz(α_k), plus on the α row (``roll_row`` (m, T, 1)) the roll's own
    velocity, b += e_z, dp += e_z × (Rz·p)."""
    c, s = torch.cos(alpha), torch.sin(alpha)

    def rz(v: Tensor, c: Tensor, s: Tensor) -> Tensor:                    # Rz·v along dim −1, pointwise
        return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], dim=-1)

    c1, s1 = c.unsqueeze(-1), s.unsqueeze(-1)
    rot = rz(rot.mT, c1, s1).mT                                           # rows of Rz·R
    pos = rz(pos, c, s)
    ang, lin = rz(ang, c1, s1), rz(lin, c1, s1)
    zero = torch.zeros_like(pos[..., :1])
    spin = torch.cat([-pos[..., 1:2], pos[..., 0:1], zero], dim=-1).unsqueeze(-2)          # e_z × p (B, m, 1, 3)
    unit_z = torch.cat([zero, zero, torch.ones_like(zero)], dim=-1).unsqueeze(-2)
    return rot, pos, ang + roll_row * unit_z, lin + roll_row * spin


def _mat3(a: Tensor, b: Tensor) -> Tensor:
    """a·b of 3 × 3 matrices (..., 3, 3) as pointwise products (no batched GEMM call)."""
    return a[..., :, 0:1] * b[..., 0:1, :] + a[..., :, 1:2] * b[..., 1:2, :] + a[..., :, 2:3] * b[..., 2:3, :]


def _matvec3(a: Tensor, x: Tensor) -> Tensor:
    """a·x for a (..., 3, 3), x (..., 3), pointwise."""
    return a[..., 0] * x[..., 0:1] + a[..., 1] * x[..., 1:2] + a[..., 2] * x[..., 2:3]


def _rotate_pairs(rot: Tensor, rows: Tensor) -> Tensor:
    """rows (B, T, 6) = (x, y) pairs of 3-vectors → (R·x, R·y), R (B, 3, 3)."""
    r = rot.unsqueeze(-3).unsqueeze(-3)                                   # (B, 1, 1, 3, 3)
    return _matvec3(r, rows.unflatten(-1, (2, 3))).flatten(-2)


def _exp_and_spatial_tangents(xi: Tensor, dxi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """exp of twists ξ = (v, ω) (..., 6) as R (..., 3, 3), p (..., 3) (:func:`~dacr_learn.lie.twist_exp`) and,
    along dξ (..., T, 6), the spatial angular velocity b = vee(dR·Rᵀ) = J_l(ω)·dω and dp (..., T, 3)."""
    v, w, dv, dw = xi[..., :3], xi[..., 3:], dxi[..., :3], dxi[..., 3:]
    phi_sq = (w * w).sum(-1)
    s, f, g, ds, df, dg = exp_coefficients_and_derivatives(phi_sq)
    w1, f1, g1 = w.unsqueeze(-2), f[..., None, None], g[..., None, None]
    dphi = 2 * (w1 * dw).sum(-1, keepdim=True)                                            # (..., T, 1)
    wv = torch.linalg.cross(w, v)
    wwv = torch.linalg.cross(w, wv)
    wdw = torch.linalg.cross(w1, dw)
    dwv = torch.linalg.cross(dw, v.unsqueeze(-2)) + torch.linalg.cross(w1, dv)
    dwwv = torch.linalg.cross(dw, wv.unsqueeze(-2)) + torch.linalg.cross(w1, dwv)
    dp = (dv + (df[..., None, None] * dphi) * wv.unsqueeze(-2) + f1 * dwv
          + (dg[..., None, None] * dphi) * wwv.unsqueeze(-2) + g1 * dwwv)
    ang = dw + f1 * wdw + g1 * torch.linalg.cross(w1, wdw)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    # R = I + s·ω^ + f·ω^², ω^² = ωωᵀ − φ²I
    rot = (1 - f * phi_sq)[..., None, None] * eye + s[..., None, None] * hat(w) \
        + f[..., None, None] * (w.unsqueeze(-1) * w.unsqueeze(-2))
    return rot, v + f.unsqueeze(-1) * wv + g.unsqueeze(-1) * wwv, ang, dp


def roll_selection(model) -> Tensor:
    """(N, m) float64 picking each rolled segment's α (a twist joint) out of the joint vector; zero columns for
    the segments that are not rolled."""
    spec = model.spec
    twist_joint = {k: spec.num_length_joints + i for i, k in enumerate(k for k, s in enumerate(spec.segments)
                                                                       if s.twists)}
    sel = torch.zeros(spec.num_joints, spec.num_segments, dtype=_F64)
    for k in torch.nonzero(model.roll).flatten().tolist():
        sel[twist_joint[k], k] = 1.0
    return sel


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

    def affine(f: Tensor) -> Tensor:
        x = norm(actuated_to_features(f, sel, fixed) / unit)             # (P, m, 4)
        return (front.with_context(x) @ w.mT + b).flatten(-2)            # (P, m·(W + O))

    d = sel.shape[0]
    probe = affine(torch.cat([torch.zeros(1, d, dtype=_F64), torch.eye(d, dtype=_F64)]))
    return (probe[1:] - probe[0]).mT.contiguous(), probe[0].clone()
