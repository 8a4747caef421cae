"""Compositional learned FK: one network learns a segment's transform, products compose the robot
(docs/compositional.md, "Model", describes each option and says why it was chosen).

A network f_θ, shared by all segments, maps the standardised per-segment Clarke features x_k = (ρ_re, ρ_im, β, α)
of segment k (non-actuated columns at β = l, α = 0) and a context c_k to the segment's transform T_k ∈ SE(3); the
robot is the product T_tip = T_1 · T_2 · … · T_m (lie.chain_products). Options: the head ``rotation`` ("twist":
T_k = exp(ξ^) of a twist ξ = (v · L_s, ω); "6d"), the roll of twisting segments (``twist_roll``: T_k =
Rz(α_k)·h(f_θ(x_k)), α weights starting at zero), ``units`` ("strain": x_k in the segment's own units and L_s = l_k,
so the network transfers, :func:`transfer`; "metric") and ``context`` ("none", "segment", "distal", "full").
"""
from __future__ import annotations

import torch
from pytorch_kinematics.transforms import rotation_6d_to_matrix
from torch import Tensor, nn

from .body import BodyPoints, body_of_points, check_points_per_segment
from .checks import check_choice, check_tensor
from .folding import activation_name
from .kinematics import effective_features
from .layers import ClarkeEncoder
from .lie import chain_products, pose_from_parts, roll_z, twist_exp
from .models import FKModel, IKModel, Standardizer, mlp
from .robot import RobotSpec

STRUCTURES = ("monolithic", "compositional")
CONTEXTS = ("none", "segment", "distal", "full")
HEADS = {"twist": 6, "6d": 9}
UNITS = ("strain", "metric")


def feature_units(spec: RobotSpec, units: str) -> Tensor:
    """(m, 4) divisors taking per-segment features (ρ_re, ρ_im, β, α) [m, m, m, rad] to network units:
    (d_k, d_k, l_k, 1) for "strain", ones for "metric". float64 (the model keeps these buffers in float64
    unless cast, so a float64 model's units are not float32-rounded; they are cast to the input's dtype)."""
    check_choice("units", units, UNITS)
    if units == "metric":
        return torch.ones(spec.num_segments, 4, dtype=torch.float64)
    return torch.tensor([[s.radius, s.radius, s.length, 1.0] for s in spec.segments], dtype=torch.float64)


def translation_units(spec: RobotSpec, units: str) -> Tensor:
    """(m,) length [m] the twist's translation part is scaled by: l_k ("strain") or the mean length ("metric")."""
    check_choice("units", units, UNITS)
    if units == "metric":
        return torch.full((spec.num_segments,), spec.total_length / spec.num_segments, dtype=torch.float64)
    return torch.tensor([s.length for s in spec.segments], dtype=torch.float64)


def alpha_inputs(context: str, num_segments: int) -> list[int]:
    """Network input columns that carry a segment's α: its own, the distal sum's with context "distal", every
    segment's with context "full" (after the m one-hot columns)."""
    if context == "full":
        return [3] + [4 + num_segments + 4 * j + 3 for j in range(num_segments)]
    return [3, 7] if context == "distal" else [3]


def append_context(x: Tensor, context: str, matrix: Tensor) -> Tensor:
    """Standardised features x (..., m, 4) → network inputs (..., m, C): x with the ``context`` appended, ``matrix``
    (m, m) its :meth:`SegmentFrontEnd.context_operator` (one-hot rows, or the distal sums)."""
    if context == "none":
        return x
    ctx = matrix.to(x.dtype)
    if context == "distal":
        return torch.cat([x, ctx @ x], dim=-1)
    extra = [ctx.expand(*x.shape[:-2], -1, -1)]
    if context == "full":
        extra.append(x.flatten(-2).unsqueeze(-2).expand(*x.shape[:-2], x.shape[-2], -1))
    return torch.cat([x, *extra], dim=-1)


class SegmentFrontEnd(nn.Module):
    """Joint vector (..., N) → per-segment network inputs (..., m, C): standardised x_k (4) and context."""

    def __init__(self, spec: RobotSpec, context: str = "none", units: str = "strain"):
        super().__init__()
        check_choice("context", context, CONTEXTS)
        self.spec, self.context, self.units, m = spec, context, units, spec.num_segments
        self.encoder = ClarkeEncoder(spec)
        self.register_buffer("unit", feature_units(spec, units))    # x_k = features / unit
        self.norm = Standardizer(4)                       # shared by all segments (pooled statistics)
        self.dim = 4 + {"none": 0, "segment": m, "distal": 4, "full": m + 4 * m}[context]
        self.register_buffer("context_matrix", self.context_operator(m, context))

    @staticmethod
    def context_operator(m: int, context: str) -> Tensor:
        """(m, m): one-hot rows ("segment", "full") or the strictly-upper ones summing the distal segments
        ("distal")."""
        return torch.eye(m) if context in ("segment", "full") else torch.ones(m, m).triu(1)

    def segment_features(self, q: Tensor) -> Tensor:
        """Unstandardised per-segment features x_k (..., m, 4) in the network's units (fixed columns at β = l,
        α = 0): (ρ/d [rad], β/l, α [rad]) for "strain", (ρ [m], β [m], α [rad]) for "metric"."""
        check_tensor(q, "joint vector", (self.spec.num_joints,))
        return effective_features(self.spec, self.encoder(q)) / self.unit.to(q.dtype)

    def fit(self, q: Tensor) -> None:
        self.norm.fit(self.segment_features(q))

    def with_context(self, x: Tensor) -> Tensor:
        """Standardised features (..., m, 4) → network inputs (..., m, C) (:func:`append_context`)."""
        return append_context(x, self.context, self.context_matrix)

    def forward(self, q: Tensor) -> Tensor:
        return self.with_context(self.norm(self.segment_features(q)))


class CompositionalFK(nn.Module):
    """Learned FK composed of per-segment transforms: joint vector (..., N) → tip pose (..., 4, 4) [m].

    ``segment_transforms`` gives T_k (..., m, 4, 4), ``segment_ends`` the end frame of every segment
    in the base frame (..., m, 4, 4). Clarke features only (raw joints do not split per segment).
    ``extra_inputs``: per-segment inputs a caller appends to the front end's (the network and skip take
    ``front.dim + extra_inputs`` columns; the hardware model's play memory); :meth:`segment_transforms`
    needs 0.
    """

    structure = "compositional"

    def __init__(self, spec: RobotSpec, features: str = "clarke", width: int = 64, depth: int = 3,
                 activation: str = "silu", rotation: str = "twist", context: str = "none", extra_inputs: int = 0,
                 units: str = "strain", twist_roll: bool = True):
        super().__init__()
        if features != "clarke":
            raise ValueError(f"features: the compositional structure needs 'clarke' features (a raw joint "
                             f"vector of a coupled robot does not split per segment), got {features!r}")
        if rotation not in HEADS:
            raise ValueError(f"rotation: expected one of {sorted(HEADS)} for the compositional structure, "
                             f"got {rotation!r}")
        if extra_inputs < 0:
            raise ValueError(f"extra_inputs: expected a number of columns >= 0, got {extra_inputs}")
        self.spec, self.rotation, self.length = spec, rotation, spec.total_length
        self.front = SegmentFrontEnd(spec, context, units)
        dim = self.front.dim + extra_inputs
        self.net = mlp(dim, HEADS[rotation], width, depth, activation)
        self.skip = nn.Linear(dim, HEADS[rotation], bias=False)              # learned linear part of f_θ
        self.register_buffer("length_scale", translation_units(spec, units))   # (m,) [m], float64
        # (m,) bool: the segments rolled by their α first (the twisting ones, if ``twist_roll``)
        self.register_buffer("roll", torch.tensor([bool(twist_roll and s.twists) for s in spec.segments]))
        self.rolls = bool(self.roll.any())
        if self.rolls:                    # start the network independent of α: the roll is the head's (see above)
            with torch.no_grad():
                for layer in (self.net[0], self.skip):
                    layer.weight[:, alpha_inputs(context, spec.num_segments)] = 0.0

    @property
    def units(self) -> str:
        return self.front.units

    def _load_from_state_dict(self, state, prefix, *args, **kwargs):
        """State dicts saved before the per-segment units (a scalar ``length_scale``, no ``front.unit``) load as
        "metric" models: the scalar is repeated per segment and the feature units are ones."""
        roll = prefix + "roll"
        if roll not in state:                       # saved before the roll of twisting segments: none rolled
            state[roll] = torch.zeros_like(self.roll)
        self.rolls = bool(state[roll].any())
        key = prefix + "length_scale"
        if key in state and state[key].dim() == 0:
            state[key] = state[key].expand(self.spec.num_segments).clone()
            state.setdefault(prefix + "front.unit", torch.ones_like(self.front.unit))
            self.front.units = "metric"
        super()._load_from_state_dict(state, prefix, *args, **kwargs)

    def fit_normalization(self, q: Tensor, pose: Tensor | None = None) -> None:
        self.front.fit(q)

    def twists(self, out: Tensor) -> Tensor:
        """Twist-head outputs (..., m, 6) → the segments' twists ξ_k = (v [m], ω [rad]) (..., m, 6)."""
        return torch.cat([out[..., :3] * self.length_scale.to(out.dtype).unsqueeze(-1), out[..., 3:]], dim=-1)

    def head(self, out: Tensor) -> Tensor:
        """Network outputs (..., m, 6 | 9) → segment transforms (..., m, 4, 4)."""
        if self.rotation == "twist":
            return twist_exp(self.twists(out))
        scale = self.length_scale.to(out.dtype).unsqueeze(-1)
        return pose_from_parts(rotation_6d_to_matrix(out[..., 3:]), out[..., :3] * scale)

    def outputs(self, q: Tensor) -> tuple[Tensor, Tensor | None]:
        """(network outputs (..., m, 6 | 9), roll α_k (..., m) [rad] of the rolled segments (0 elsewhere), or None
        when no segment is rolled) of joint vectors (..., N)."""
        x = self.front.segment_features(q)
        z = self.front.with_context(self.front.norm(x))
        return self.net(z) + self.skip(z), torch.where(self.roll, x[..., 3], 0.0) if self.rolls else None

    def segment_transforms(self, q: Tensor) -> Tensor:
        """T_k, base of segment k → its end: (..., N) → (..., m, 4, 4); Rz(α_k)·head for a rolled segment."""
        out, alpha = self.outputs(q)
        t = self.head(out)
        return t if alpha is None else roll_z(t, alpha)

    def body(self, q: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The learned body of joint vectors q (..., N): points (..., 1 + m·K, 3) [m] in the base frame, the layout
        of :mod:`dacr_learn.body`. Segment k's point at fraction s = j/K is Rz(α_k)·exp(s·ξ_k) after the ends of
        the segments before it: the segment's own learned twist, followed part of the way (a constant-curvature
        arc, rolled by its twist, is exactly that curve). Needs the "twist" head (ValueError for "6d")."""
        if self.rotation != "twist":
            raise ValueError(f"{type(self).__name__}: has no body: the {self.rotation!r} head gives a segment's end "
                             "transform but not the curve to it; train with rotation 'twist'")
        k = check_points_per_segment(points_per_segment)
        out, alpha = self.outputs(q)
        xi = self.twists(out)
        frac = torch.arange(1, k + 1, dtype=xi.dtype, device=xi.device) / k
        partial = twist_exp(xi.unsqueeze(-2) * frac.unsqueeze(-1),                    # (..., m, K, 4, 4)
                            None if alpha is None else alpha.unsqueeze(-1).expand(*alpha.shape, k))
        ends = chain_products(partial[..., -1, :, :])                                 # (..., m, 4, 4)
        eye = torch.eye(4, dtype=xi.dtype, device=xi.device).expand(*ends.shape[:-3], 1, 4, 4)
        bases = torch.cat([eye, ends[..., :-1, :, :]], dim=-3).unsqueeze(-3)          # (..., m, 1, 4, 4)
        pts = (bases[..., :3, :3] @ partial[..., :3, 3:] + bases[..., :3, 3:]).squeeze(-1)   # (..., m, K, 3)
        pts = pts.flatten(-3, -2)
        return body_of_points(self.spec, torch.cat([torch.zeros_like(pts[..., :1, :]), pts], dim=-2), k)

    def segment_ends(self, q: Tensor) -> Tensor:
        """End frame of every segment in the robot base frame: (..., N) → (..., m, 4, 4); [..., -1] is the tip."""
        return chain_products(self.segment_transforms(q))

    def forward(self, q: Tensor) -> Tensor:
        return self.segment_ends(q)[..., -1, :, :]


def build_fk_model(spec: RobotSpec, structure: str = "monolithic", context: str = "none", units: str = "strain",
                   body_points: int = 0, body_prior: str = "none", **kwargs) -> FKModel | CompositionalFK:
    """An FK model of the given ``structure`` ("monolithic" | "compositional"); ``kwargs`` are the shared
    model arguments (features, width, depth, activation, rotation). ``context`` and ``units`` are the
    compositional model's (the monolithic model takes their defaults only); ``body_points`` and ``body_prior`` the
    monolithic model's shape output (the compositional model's body comes from its segment twists: 0 only)."""
    check_choice("structure", structure, STRUCTURES)
    if structure == "compositional":
        if body_points:
            raise ValueError(f"body_points: the compositional model's body comes from its segment twists (no shape "
                             f"output); expected 0, got {body_points}")
        return CompositionalFK(spec, context=context, units=units, **kwargs)
    if context != "none":
        raise ValueError(f"context: only the compositional structure takes a context, got {context!r}")
    if units != "strain":
        raise ValueError(f"units: only the compositional structure takes units, got {units!r}")
    return FKModel(spec, body_points=body_points, body_prior=body_prior, **kwargs)


# hyper-parameters a FKModule / IKModule checkpoint must hold to rebuild its network without Lightning
REQUIRED_HPARAMS = {"fk": ("features", "width", "depth", "activation", "rotation"),
                    "ik": ("features", "width", "depth", "activation"),
                    "sampler": ("features", "width", "depth", "activation", "transforms", "bins")}


def model_from_hparams(task: str, spec: RobotSpec, hparams) -> nn.Module:
    """The (untrained) network of an FK / IK / sampler module with these hyper-parameters (a mapping with the keys of
    :data:`REQUIRED_HPARAMS`; ``structure``, ``context``, ``units``, ``output_scale`` default as in training).
    ``training.FKModule`` / ``IKModule`` build theirs with it, and :func:`dacr_learn.runs.load_checkpoint_model`
    rebuilds a checkpoint's without Lightning."""
    h = hparams
    if task == "fk":
        return build_fk_model(spec, h.get("structure", "monolithic"), h.get("context", "none"),
                              h.get("units", "strain"), h.get("body_points", 0), h.get("body_prior", "none"),
                              features=h["features"], width=h["width"], depth=h["depth"],
                              activation=h["activation"], rotation=h["rotation"])
    if task == "ik":
        return IKModel(spec, h["features"], h["width"], h["depth"], h["activation"], h.get("output_scale", "std"))
    if task == "sampler":
        from .sampler import ClarkeSampler
        return ClarkeSampler(spec, h["features"], h["transforms"], h["width"], h["depth"], h["activation"], h["bins"])
    raise ValueError(f"task: expected 'fk', 'ik' or 'sampler', got {task!r}")


def _geometry(seg) -> tuple:
    return seg.type, seg.length, seg.radius, seg.bend, seg.length_range, seg.twist_range


ROBOT_BUFFERS = ("front.encoder.", "front.context_matrix", "front.unit", "length_scale", "roll")   # from the spec


def transfer(model: CompositionalFK, target: RobotSpec) -> CompositionalFK:
    """The trained per-segment network of ``model``, unchanged, composed over the segments of ``target``
    (docs/compositional.md, "Transfer to other robots"). "strain" units: target segments of any type, length, radius
    and joint layout (its error grows where their features leave the training range); one that extends or twists
    needs a source segment that does (ValueError). "metric" units: each target segment must have the geometry (type,
    length, radius, limits) of some source segment. Contexts "segment" and "full" cannot transfer."""
    if model.front.context in ("segment", "full"):
        raise ValueError(f"transfer: a model with context {model.front.context!r} has inputs per source segment index; "
                         "train with context 'none' or 'distal' to transfer to another number of segments")
    for flag, what in (("extends", "extend (type I/III)"), ("twists", "twist (type II/III)")):
        new_axes = [k for k, s in enumerate(target.segments) if getattr(s, flag)]
        if new_axes and not any(getattr(s, flag) for s in model.spec.segments):
            raise ValueError(f"transfer: segments {new_axes} of {target.name!r} {what}, but no segment of the "
                             f"training robot {model.spec.name!r} does, so the network never saw that feature "
                             f"vary; train on a robot with such a segment")
    if model.units == "metric":
        known = {_geometry(s) for s in model.spec.segments}
        unknown = [k for k, s in enumerate(target.segments) if _geometry(s) not in known]
        if unknown:
            raise ValueError(f"transfer: segments {unknown} of {target.name!r} have a geometry none of the "
                             f"training robot {model.spec.name!r} has (type, length, radius, limits); "
                             f"expected one of {sorted(known, key=str)}, or a model trained with units 'strain'")
    net = model.net
    new = CompositionalFK(target, "clarke", net[0].out_features, len(net) // 2, activation_name(net),
                          model.rotation, model.front.context, units=model.units,
                          twist_roll=model.rolls or not any(s.twists for s in model.spec.segments),
                          ).to(next(model.parameters()).dtype)
    state = {k: v for k, v in model.state_dict().items() if not k.startswith(ROBOT_BUFFERS)}
    state["roll"] = new.roll                          # the target's (a missing key means a state dict before it)
    missing, unexpected = new.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith(ROBOT_BUFFERS) for k in missing):
        raise RuntimeError(f"transfer: state-dict mismatch: missing {missing}, unexpected {unexpected}")
    return new
