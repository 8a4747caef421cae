"""Neural FK / IK models with a feature front-end chosen by name (docs/design.md §5).

Front-ends ("clarke" | "raw"):
- clarke: ClarkeEncoder → only the actuated columns (ρ_re, ρ_im per segment, β and α where
  actuated), standardised with training-set statistics;
- raw: the joint vector itself, standardised with training-set statistics.

FKModel: joint vector (..., num_joints) → tip pose (..., 4, 4) [m]; the network predicts the
position divided by the total robot length and the rotation as 6D (Zhou et al., the first two
rows of R) or as a quaternion (w, x, y, z); conversions via pytorch_kinematics.transforms.
IKModel: tip pose (..., 4, 4) → joint vector. With "clarke" it predicts the actuated features
and decodes them with ClarkeDecoder, so every output satisfies the displacement constraint by
construction; with "raw" it predicts the joint vector directly (the ablation's baseline).
"""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import quaternion_to_matrix, rotation_6d_to_matrix
from torch import Tensor, nn

from .body import BodyPoints, body_of_points, check_points_per_segment, subsample
from .checks import check_choice, check_tensor
from .kinematics import backbone_points, forward_kinematics
from .layers import ClarkeDecoder, ClarkeEncoder
from .lie import pose_from_parts
from .robot import RobotSpec

FEATURE_MODES = ("clarke", "raw")
BODY_PRIORS = ("none", "cc")
ROTATIONS = {"6d": (6, rotation_6d_to_matrix), "quaternion": (4, quaternion_to_matrix)}
ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU, "gelu": nn.GELU, "tanh": nn.Tanh}


def mlp(in_dim: int, out_dim: int, width: int, depth: int, activation: str) -> nn.Sequential:
    """``depth`` hidden layers of ``width`` units with ``activation``, then a linear output layer."""
    check_choice("activation", activation, ACTIVATIONS)
    if width < 1 or depth < 1:
        raise ValueError(f"width/depth: expected >= 1, got width={width}, depth={depth}")
    layers, d = [], in_dim
    for _ in range(depth):
        layers += [nn.Linear(d, width), ACTIVATIONS[activation]()]
        d = width
    return nn.Sequential(*layers, nn.Linear(d, out_dim))


class Standardizer(nn.Module):
    """x ↦ (x − mean)/std with buffers fitted on training data; ``inverse`` undoes it. (..., D)."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    def fit(self, x: Tensor, dtype: torch.dtype = torch.float64) -> None:
        """Mean and std over all leading dims of x (..., D), computed in ``dtype`` and stored in the buffers' dtype
        (std clamped at 1e-6 of the largest + 1e-12)."""
        x = x.reshape(-1, x.shape[-1]).to(dtype)
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-12 + 1e-6 * x.std(0).max().item()))

    def forward(self, x: Tensor) -> Tensor:
        return (x - self.mean) / self.std

    def inverse(self, z: Tensor) -> Tensor:
        return z * self.std + self.mean


FEATURE_COLUMNS = ("rho_re", "rho_im", "beta", "alpha")


def actuated_columns(spec: RobotSpec) -> list[tuple[int, str]]:
    """(segment, column name) of each actuated feature, in the order used everywhere (length D):
    per segment ρ_re, ρ_im, then β if it extends and α if it twists."""
    cols = []
    for k, seg in enumerate(spec.segments):
        cols += [(k, "rho_re"), (k, "rho_im")] + [(k, "beta")] * seg.extends + [(k, "alpha")] * seg.twists
    return cols


def actuated_selection(spec: RobotSpec) -> Tensor:
    """(D, 4m) 0/1 matrix picking the actuated columns out of a flattened feature tensor."""
    flat = [4 * k + FEATURE_COLUMNS.index(name) for k, name in actuated_columns(spec)]
    return torch.eye(4 * spec.num_segments)[flat]


def fixed_features(spec: RobotSpec, dtype: torch.dtype = torch.float32) -> Tensor:
    """(m, 4) feature tensor holding only the fixed values (β = l where β is not actuated), zero
    in every actuated column: fixed_features + actuated @ actuated_selection is a full feature tensor."""
    return torch.tensor([[0.0, 0.0, 0.0 if s.extends else s.length, 0.0] for s in spec.segments], dtype=dtype)


def actuated_to_features(actuated: Tensor, selection: Tensor, fixed: Tensor) -> Tensor:
    """Actuated features (..., D) → full feature tensor (..., m, 4): the ``fixed`` values (m, 4)
    plus the actuated values scattered by ``selection`` (D, 4m) (see :func:`actuated_selection`)."""
    flat = fixed.flatten().to(actuated.dtype) + actuated @ selection.to(actuated.dtype)
    return flat.unflatten(-1, tuple(fixed.shape))


class FeatureFrontEnd(nn.Module):
    """Joint vector (..., num_joints) → standardised input features (..., D) for a network."""

    def __init__(self, spec: RobotSpec, mode: str = "clarke"):
        super().__init__()
        check_choice("features", mode, FEATURE_MODES)
        self.spec, self.mode = spec, mode
        self.encoder = ClarkeEncoder(spec) if mode == "clarke" else None
        if mode == "clarke":
            self.register_buffer("selection", actuated_selection(spec))
        self.dim = spec.num_actuated_features if mode == "clarke" else spec.num_joints
        self.norm = Standardizer(self.dim)

    def raw_features(self, q: Tensor) -> Tensor:
        """Unstandardised features (..., D): actuated Clarke columns [m, rad] or the joint vector."""
        check_tensor(q, "joint vector", (self.spec.num_joints,))
        if self.encoder is None:
            return q
        return self.encoder(q).flatten(-2) @ self.selection.to(q.dtype).mT

    def fit(self, q: Tensor) -> None:
        self.norm.fit(self.raw_features(q))

    def forward(self, q: Tensor) -> Tensor:
        return self.norm(self.raw_features(q))


def pose_to_vector(pose: Tensor, length: float) -> Tensor:
    """Pose (..., 4, 4) → (..., 9): position / total length and the 6D rotation (first two rows)."""
    return torch.cat([pose[..., :3, 3] / length, pose[..., :2, :3].flatten(-2)], dim=-1)


class FKModel(nn.Module):
    """Learned forward kinematics: joint vector (..., num_joints) → tip pose (..., 4, 4) [m].

    ``body_points`` K > 0 adds a shape output (docs/body.md): a second network of the same shape (``body_net``, on
    the same input features) predicting the body's 1 + m·K points (the layout of :mod:`dacr_learn.body`) divided by
    the total length, ``body_prior`` "none", or "cc": their offsets from the CC arcs of the joint vector's features
    (:func:`~dacr_learn.kinematics.backbone_points`). :meth:`body` returns them; the tip network is untouched by it
    (0: no shape output, the model and its state dict as before). The body's last point is the shape output's own tip.
    """

    structure = "monolithic"     # one network for the whole robot (vs compositional.CompositionalFK)

    def __init__(self, spec: RobotSpec, features: str = "clarke", width: int = 256, depth: int = 3,
                 activation: str = "silu", rotation: str = "6d", body_points: int = 0, body_prior: str = "none"):
        super().__init__()
        check_choice("rotation", rotation, ROTATIONS)
        if isinstance(body_points, bool) or not isinstance(body_points, int) or body_points < 0:
            raise ValueError(f"body_points: expected an integer >= 0 (points per segment of the shape output; "
                             f"0: none), got {body_points!r}")
        check_choice("body_prior", body_prior, BODY_PRIORS)
        self.spec, self.rotation, self.body_points, self.body_prior = spec, rotation, body_points, body_prior
        self.front = FeatureFrontEnd(spec, features)
        self.net = mlp(self.front.dim, 3 + ROTATIONS[rotation][0], width, depth, activation)
        self.length = spec.total_length
        if body_points:
            self.body_net = mlp(self.front.dim, 3 * spec.num_segments * body_points, width, depth, activation)
            if body_prior == "cc":
                self.body_encoder = ClarkeEncoder(spec)
                with torch.no_grad():                   # start at the CC arcs
                    self.body_net[-1].weight.zero_()
                    self.body_net[-1].bias.zero_()

    def body(self, q: Tensor, points_per_segment: int | None = None) -> BodyPoints:
        """The learned body of joint vectors q (..., num_joints) (the shape output): ``points_per_segment`` K'
        (None: the trained K) must divide the trained K (every K/K'-th point); ValueError without a shape output."""
        if not self.body_points:
            raise ValueError(f"{type(self).__name__}: has no body: trained without a shape output; train with "
                             "model.init_args.body_points K > 0 and body_weight > 0 on data with backbones")
        k = self.body_points if points_per_segment is None else check_points_per_segment(points_per_segment)
        if self.body_points % k:
            raise ValueError(f"points_per_segment: the shape output has {self.body_points} points per segment; "
                             f"expected a divisor of it, got {k}")
        pts = (self.body_net(self.front(q)) * self.length).unflatten(-1, (-1, 3))
        pts = torch.cat([torch.zeros_like(pts[..., :1, :]), pts], dim=-2)
        if self.body_prior == "cc":
            pts = pts + backbone_points(self.spec, self.body_encoder(q), self.body_points)
        return body_of_points(self.spec, subsample(pts, self.spec.num_segments, self.body_points // k), k)

    def fit_normalization(self, q: Tensor, pose: Tensor | None = None) -> None:
        self.front.fit(q)

    def forward(self, q: Tensor) -> Tensor:
        out = self.net(self.front(q))
        rot = ROTATIONS[self.rotation][1](out[..., 3:])
        return pose_from_parts(rot, out[..., :3] * self.length)


OUTPUT_SCALES = ("std", "task")


class IKModel(nn.Module):
    """Learned inverse kinematics: tip pose (..., 4, 4) → joint vector (..., num_joints).

    ``output_scale``: how the network output z is standardised, y = mean + scale·z. "std": the training
    targets' standard deviations. "task": scales that make one unit of every output move the tip pose
    alike (median over training samples of ‖∂v/∂z_i‖, v = :func:`pose_to_vector`, equal for all i;
    geometric mean of scale/std = 1), so a feature MSE weighs each output by its effect on the tip and
    the pose-loss gradient is balanced across outputs (see :meth:`fit_normalization`).
    """

    def __init__(self, spec: RobotSpec, features: str = "clarke", width: int = 256, depth: int = 3,
                 activation: str = "silu", output_scale: str = "std"):
        super().__init__()
        check_choice("features", features, FEATURE_MODES)
        check_choice("output_scale", output_scale, OUTPUT_SCALES)
        self.spec, self.features, self.length, self.output_scale = spec, features, spec.total_length, output_scale
        self.in_norm = Standardizer(9)
        self.encoder, self.decoder = ClarkeEncoder(spec), ClarkeDecoder(spec)
        if features == "clarke":
            self.register_buffer("selection", actuated_selection(spec))
            self.register_buffer("base_features", fixed_features(spec))
        out_dim = spec.num_actuated_features if features == "clarke" else spec.num_joints
        self.out_norm = Standardizer(out_dim)
        self.net = mlp(9, out_dim, width, depth, activation)

    def target(self, q: Tensor) -> Tensor:
        """Unstandardised regression target (..., D) of a joint vector: actuated features or q."""
        if self.features == "raw":
            return q
        return self.encoder(q).flatten(-2) @ self.selection.to(q.dtype).mT

    def fit_normalization(self, q: Tensor, pose: Tensor, num_jacobian: int = 256) -> None:
        """Input and output standardisation from training joint vectors (N, num_joints) and poses (N, 4, 4);
        "task" output scales from the pose Jacobian at the first ``num_jacobian`` samples (float64)."""
        self.in_norm.fit(pose_to_vector(pose, self.length))
        self.out_norm.fit(self.target(q))
        if self.output_scale == "task":
            self.out_norm.std.copy_(self.task_scale(q[:num_jacobian]))

    def task_scale(self, q: Tensor) -> Tensor:
        """Output scales (D,) of the "task" standardisation at joint vectors q (B, num_joints) (see class)."""
        std = self.out_norm.std.double()
        to_features = ClarkeEncoder(self.spec).double() if self.features == "raw" else (
            lambda y: actuated_to_features(y, self.selection.double(), self.base_features.double()))
        jac = torch.autograd.functional.jacobian(                      # (9, B, D)
            lambda y: pose_to_vector(forward_kinematics(self.spec, to_features(y)), self.length).sum(0),
            self.target(q.double()).detach())
        gain = jac.norm(dim=0).median(dim=0).values                  # (D,) pose change per unit of y_i
        scale = 1 / gain.clamp_min(1e-12 * gain.max().item())
        return (scale * torch.exp(torch.log(std / scale).mean())).to(self.out_norm.std.dtype)

    def normalized_input(self, pose: Tensor) -> Tensor:
        """Poses (..., 4, 4) [m] → the network's standardised input vectors (..., 9)."""
        check_tensor(pose, "pose", (4, 4))
        return self.in_norm(pose_to_vector(pose, self.length))

    def input_pose(self, x: Tensor) -> Tensor:
        """Standardised input vectors (..., 9) → the poses (..., 4, 4) [m] they encode: the position, and the
        rotation whose first two rows are the Gram–Schmidt orthonormalisation of the 6D part (exact inverse of
        :meth:`normalized_input` on its image; any vector, e.g. a perturbed input, maps to a valid pose)."""
        v = self.in_norm.inverse(x)
        return pose_from_parts(rotation_6d_to_matrix(v[..., 3:]), v[..., :3] * self.length)

    def forward_normalized(self, pose: Tensor) -> Tensor:
        return self.net(self.normalized_input(pose))

    def decode(self, z: Tensor) -> Tensor:
        """Standardised network output (..., D) → joint vector (..., num_joints)."""
        return self.out_norm.inverse(z) if self.features == "raw" else self.decoder(self.decode_features(z))

    def decode_features(self, z: Tensor) -> Tensor:
        """Standardised network output (..., D) → full Clarke feature tensor (..., m, 4) of the predicted
        joint vector: "clarke" scatters the actuated columns (= encoder(decode(z)) without the
        round trip), "raw" encodes the predicted joint vector (its least-squares projection onto
        the displacement constraint). Differentiable; the input of the analytic FK in pose losses."""
        y = self.out_norm.inverse(z)
        if self.features == "raw":
            return self.encoder(y)
        return actuated_to_features(y, self.selection, self.base_features)

    def forward(self, pose: Tensor) -> Tensor:
        return self.decode(self.forward_normalized(pose))
