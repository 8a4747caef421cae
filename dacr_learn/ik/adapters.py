"""What the IK solver needs of a model: its variables, their limits, the tip and its Jacobian, and a check.

The solver iterates on variables x (B, D) inside :class:`~dacr_learn.limits.Limits` and returns joint vectors.
For a robot described by a :class:`~dacr_learn.robot.RobotSpec` the variables are the actuated Clarke features
f (ρ_re, ρ_im per segment, β and α where actuated; ``models.actuated_columns`` order): the bending limit of a
segment is then a disk and its length and twist ranges boxes, and every joint vector the decoder returns lies
on the displacement constraint by construction.

- :class:`ConstantCurvature`: the analytic CC model of a robot file (closed-form Jacobian, :mod:`~dacr_learn.lie`).
- :class:`LearnedFK`: a trained FK model (monolithic, compositional, Cosserat-trained): the same variables,
  the tip of the network; the Jacobian from the folded inference module where one exists, else forward-mode
  autodiff. Its accuracy is with respect to the network, not the robot.
- a saved hardware model: servo commands [mm] inside the recorded range → tip position
  (:class:`dacr_learn.hardware.deploy.ik.HardwareTip`, registered for ``HardwareModel`` by that module).

Every model also gives :meth:`SolverModel.check`: the tip, the limits and the constraint residual of a
joint vector computed from the joints alone (encoder → FK), not from the solver's internal variables.
All float64.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..body import BodyPoints, cc_body
from ..checks import F64
from ..clarke_space import ClarkeSpace
from ..kinematics import cc_pose_and_jacobian, forward_kinematics
from ..lie import twist_jacobian
from ..limits import Limits
from ..models import FEATURE_COLUMNS, actuated_columns, actuated_to_features
from ..robot import RobotSpec


@dataclass
class Check:
    """Independent check of joint vectors q (B, N): tip position (B, 3) [m], rotation (B, 3, 3) or None
    (position-only models), inside every limit (B,) bool, displacement-constraint residual (B,) [m]."""

    position: Tensor
    rotation: Tensor | None
    inside: Tensor
    constraint: Tensor


class TipJacobian(NamedTuple):
    """What :meth:`SolverModel.tip_and_jacobian` returns for variables x (B, D), float64: the tip ``position``
    (B, 3) [m], its ``rotation`` (B, 3, 3) or None (position-only models), and ``jacobian`` (B, 6 or 3, D): the
    tip point's velocity (then angular velocity) in the base frame per unit of each variable. A tuple: ``pos, rot,
    jac = model.tip_and_jacobian(x)`` unpacks it."""

    position: Tensor
    rotation: Tensor | None
    jacobian: Tensor


class SolverModel:
    """Interface of a model the IK solver can invert (see the module docstring).

    Attributes: ``limits`` (:class:`~dacr_learn.limits.Limits` on the D variables), ``rest`` (D,) the rest
    configuration (solutions nearer to it come first), ``length`` (position scale [m]: the
    solver weighs position errors in units of it against rotation errors in rad), ``has_rotation`` (False for
    tip-position models), ``num_joints`` N, ``spec`` (the RobotSpec, or None).
    """

    limits: Limits
    length: float
    rest: Tensor
    has_rotation: bool = True
    num_joints: int
    spec: RobotSpec | None = None

    def tip_and_jacobian(self, x: Tensor) -> TipJacobian:
        """Variables (B, D) → :class:`TipJacobian` (tip position, rotation or None, Jacobian)."""
        raise NotImplementedError

    def joints(self, x: Tensor) -> Tensor:
        """Variables (B, D) → joint vector (B, N) [m, rad] (servo commands [mm] for a hardware model)."""
        raise NotImplementedError

    def variables(self, q: Tensor) -> Tensor:
        """Joint vector (B, N) → variables (B, D) (a warm start)."""
        raise NotImplementedError

    def check(self, q: Tensor) -> Check:
        raise NotImplementedError

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """Points on the robot's body at variables x (B, D), differentiable in x (:class:`~dacr_learn.body.BodyPoints`:
        points (B, 1 + m·K, 3) [m] in the model's base frame — the arm's base frame for an arm composite —, their
        arc length (P,) and envelope radius (P,); K = ``points_per_segment``). Collision-free IK (``solve_ik(...,
        scene=)``) needs it. A model without a body raises ValueError."""
        raise ValueError(f"{type(self).__name__}: has no body: this model knows its tip only (collision checks "
                         f"need a model with a backbone, e.g. the analytic CC model of a robot file)")

    def links(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """Rigid links around the body (an arm's) at variables x (B, D) as capsules: ends a, b (B, C, 3) [m], radius
        (C,) [m], near_mount (C,) bool (not checked against the robot's body); None for a robot alone."""
        return None


class _ClarkeVariables(SolverModel):
    """Actuated Clarke features of a RobotSpec as the variables: limits, decoder and encoder."""

    def __init__(self, spec: RobotSpec):
        self.spec, self.num_joints, self.length = spec, spec.num_joints, spec.total_length
        self.space = ClarkeSpace(spec)
        self.limits = self.space.limits
        self.rest = self.space.fold.e0.to(F64)           # the straight robot at nominal lengths, no twist

    def joints(self, x: Tensor) -> Tensor:
        return self.space.joints(x)

    def variables(self, q: Tensor) -> Tensor:
        return self.space.features(q)

    def _features_check(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(actuated features (B, D), inside (B,), constraint residual (B,) [m]) of joint vectors q."""
        f = self.space.features(q)
        residual = (self.space.joints(f) - q).abs().amax(-1)
        return f, self.limits.inside(f), residual


class ConstantCurvature(_ClarkeVariables):
    """The analytic constant-curvature model of a robot: features → tip pose and its closed-form Jacobian."""

    def __init__(self, spec: RobotSpec):
        super().__init__(spec)
        self._columns = [(k, FEATURE_COLUMNS.index(name)) for k, name in actuated_columns(spec)]

    def features(self, x: Tensor) -> Tensor:
        return actuated_to_features(x, self.space.selection, self.space.base)

    def tip_and_jacobian(self, x: Tensor) -> TipJacobian:
        pose, jac = cc_pose_and_jacobian(self.spec, self.features(x), self._columns)
        return TipJacobian(pose[..., :3, 3], pose[..., :3, :3], jac)

    def check(self, q: Tensor) -> Check:
        f, inside, residual = self._features_check(q)
        pose = forward_kinematics(self.spec, self.features(f))
        return Check(pose[..., :3, 3], pose[..., :3, :3], inside, residual)

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The exact constant-curvature arcs (:func:`~dacr_learn.body.cc_body`) in the robot's base frame."""
        return cc_body(self.spec, self.features(x), points_per_segment)


class LearnedFK(_ClarkeVariables):
    """A trained FK model (joint vector → tip pose) inverted in Clarke space.

    ``model``: an ``FKModel`` or ``CompositionalFK`` (e.g. ``dacr_learn.load_model(run)``), evaluated in
    float64. The Jacobian w.r.t. the features comes from the folded inference module
    (:class:`~dacr_learn.inference.InferenceJacobian`, or the compositional one for a twist head) when it can
    be built, else from forward-mode autodiff through ``model(decoder(f))``.
    """

    def __init__(self, model: nn.Module):
        super().__init__(model.spec)
        self.model = model.to(F64).eval()
        self.jacobian_module = _folded_jacobian(self.model)

    def tip_and_jacobian(self, x: Tensor) -> TipJacobian:
        if self.jacobian_module is not None:
            pose, jac_f, _ = self.jacobian_module(self.joints(x))
            return TipJacobian(pose[..., :3, 3], pose[..., :3, :3], jac_f)
        with torch.no_grad():
            pose = self.model(self.joints(x))
        dpose = torch.func.vmap(torch.func.jacfwd(lambda f: self.model(self.joints(f.unsqueeze(0)))[0]))(x)
        return TipJacobian(pose[..., :3, 3], pose[..., :3, :3], twist_jacobian(pose, dpose))

    @torch.no_grad()
    def check(self, q: Tensor) -> Check:
        _, inside, residual = self._features_check(q)
        pose = self.model(q.to(F64))
        return Check(pose[..., :3, 3], pose[..., :3, :3], inside, residual)

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The network's learned body (the compositional model's segment twists, an FK model's shape output). A
        shape output of K points per segment serves the largest divisor of K not above ``points_per_segment``
        (a denser request gets its K points: the swept-body bound then spans longer chords)."""
        if not hasattr(self.model, "body"):
            raise ValueError(f"{type(self.model).__name__}: has no body")
        trained = getattr(self.model, "body_points", 0)
        if trained:
            points_per_segment = max(k for k in range(1, trained + 1)
                                     if trained % k == 0 and k <= max(points_per_segment, 1))
        return self.model.body(self.joints(x), points_per_segment)


def _folded_jacobian(model: nn.Module) -> nn.Module | None:
    """The folded Jacobian module of a trained FK model in float64, or None where there is none."""
    from ..compositional import CompositionalFK
    from ..deploy.inference import InferenceJacobian
    from ..deploy.inference_compositional import InferenceCompositionalJacobian
    if isinstance(model, CompositionalFK):
        return InferenceCompositionalJacobian(model, F64) if model.rotation == "twist" else None
    return InferenceJacobian(model, F64)


ADAPTERS: dict[type, Callable[[object], SolverModel]] = {}
"""Model classes of higher layers and the SolverModel each becomes (:func:`register_solver_model`)."""


def register_solver_model(cls: type, factory: Callable[[object], SolverModel]) -> None:
    """Let :func:`as_solver_model` (and so ``solve_ik``) accept instances of ``cls``, turned into a SolverModel by
    ``factory`` (modules above this layer register their models here, e.g. the hardware models)."""
    ADAPTERS[cls] = factory


def as_solver_model(model) -> SolverModel:
    """A :class:`SolverModel` of a RobotSpec (or a robot YAML path / dict: the analytic CC model), a trained FK
    model, a loaded hardware model, or a SolverModel (returned as is). ValueError for anything else."""
    if isinstance(model, SolverModel):
        return model
    for cls, factory in ADAPTERS.items():                           # e.g. a saved hardware model
        if isinstance(model, cls):
            return factory(model)
    if isinstance(model, nn.Module) and isinstance(getattr(model, "spec", None), RobotSpec):
        return LearnedFK(model)
    try:
        spec = RobotSpec.coerce(model)
    except (TypeError, ValueError) as err:
        raise ValueError(f"model_or_spec: expected a RobotSpec, a robot YAML file or dict, a trained FK model or "
                         f"an ik.SolverModel, got {type(model).__name__} ({err})") from err
    return ConstantCurvature(spec)
