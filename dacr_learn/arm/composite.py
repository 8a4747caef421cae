"""An arm carrying a continuum robot: one batched, differentiable model with a closed-form whole-body Jacobian.

World frame: the arm's base. With θ (n,) the arm's joints, T_a(θ) its tip link's pose (pytorch-kinematics), M the
fixed mount (tip link → robot base) and T_c(x_c) the continuum robot's tip pose (any
:class:`~dacr_learn.ik.SolverModel`), the whole-body tip pose is

    T(θ, x_c) = T_a(θ) · M · T_c(x_c),   p = p_b + R_b·p_c,  R = R_b·R_c,  (R_b, p_b) = T_a·M (the robot base).

The joint vector, the IK variables and their limits, and the columns of the closed-form Jacobian (arm: shifted to
the continuum tip; robot: rotated into the world): docs/arm.md, "The model". :class:`Composite` is a
:class:`~dacr_learn.ik.SolverModel`, so ``solve_ik`` inverts it unchanged. Float64 throughout.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..body import BodyPoints, transform_body
from ..checks import F64
from ..ik.adapters import Check, ConstantCurvature, LearnedFK, SolverModel, TipJacobian, as_solver_model
from ..ik.targets import pose_defects
from ..kinematics import forward_kinematics
from ..limits import Limits
from .chain import Arm
from .geometry import posed_capsules
from .seeds import PoseBank

BANK_SIZE = 8192   # samples of the pose bank that seeds whole-body IK (docs/arm.md: about 0.1 s to build)


class WholeBody(NamedTuple):
    """One evaluation of a :class:`Composite` at variables (B, n + D), world (arm base) frame: tip ``position``
    (B, 3) [m], ``rotation`` (B, 3, 3) or None (position-only robot), ``jacobian`` (B, 6 or 3, n + D) of the
    tip (module docstring), the robot ``base`` pose T_a·M (B, 4, 4) and ``base_jacobian`` (B, 3, n + D): the
    velocity of the base point (zero in the robot's columns), or None when not asked for."""

    position: Tensor
    rotation: Tensor | None
    jacobian: Tensor
    base: Tensor
    base_jacobian: Tensor | None


def check_mount(mount) -> Tensor:
    """A mount (4, 4) as float64: a homogeneous transform (:func:`~dacr_learn.ik.targets.pose_defects`, as the
    solver asks of a target pose; finite), used as given. ValueError naming what is
    wrong."""
    m = torch.as_tensor(mount)
    if not m.is_floating_point() or m.shape != (4, 4):
        raise ValueError(f"mount: expected a float (4, 4) homogeneous transform (tip link → robot base), got "
                         f"{m.dtype} {tuple(m.shape)}")
    m = m.to(F64)
    if not torch.isfinite(m).all():
        raise ValueError("mount: has NaN/inf entries")
    orth, det, wrong = pose_defects(m)
    if wrong:
        raise ValueError(f"mount: the rotation block must be a rotation (RRᵀ = I, det +1 to 1e-6) and the last row "
                         f"(0, 0, 0, 1); got |RRᵀ − I| = {float(orth):.2e}, det = {float(det):.9f}, last row "
                         f"{m[3].tolist()}")
    return m


class Composite(SolverModel):
    """Arm + mount + continuum robot as one model (module docstring).

    arm: an :class:`~.chain.Arm` (:func:`~.chain.load_arm`); mount (4, 4): tip link → robot base [m];
    robot: a continuum model (a RobotSpec / robot YAML — the analytic CC model —, a trained FK model, a hardware
    model or any SolverModel: see :func:`~dacr_learn.ik.as_solver_model`); home (n,): the arm configuration
    solutions are ordered by closeness to (with the straight robot: :attr:`rest`; default: the middle of
    each joint's range).

    Attributes: ``num_arm`` n, ``num_joints`` n + N, ``limits`` (θ boxes, then the robot's limits),
    ``rest``, ``length`` (position scale of the solver [m]: the arm's link-offset lengths + the mount's
    offset + the robot's length), ``has_rotation`` (the robot's).
    """

    def __init__(self, arm: Arm, mount, robot, home: Tensor | None = None):
        self.arm, self.mount, self.robot = arm, check_mount(mount), as_solver_model(robot)
        self.num_arm = n = arm.num_joints
        self.num_joints = n + self.robot.num_joints
        self.has_rotation = self.robot.has_rotation
        self.spec = None
        a, r = arm.limits, self.robot.limits
        self.limits = Limits.concatenate(a, r, names=a.names + tuple(f"robot.{x}" for x in r.names))
        if home is None:
            home = (a.lower + a.upper) / 2
        home = torch.as_tensor(home, dtype=F64)
        if home.shape != (n,) or not torch.isfinite(home).all() or not bool(a.inside(home)):
            raise ValueError(f"home: expected {n} finite arm joint values inside the URDF limits, got {home.tolist()}")
        self.home = home
        self.rest = torch.cat([home, self.robot.rest.to(F64)])
        offsets = arm.chain.forward_kinematics_tensor(torch.zeros(1, n, dtype=F64), analytical_grad=False)
        reach = torch.linalg.vector_norm(offsets[1:, 0, :3, 3] - offsets[:-1, 0, :3, 3], dim=-1).sum()
        self._bank = None
        self.length = float(reach) + float(torch.linalg.vector_norm(self.mount[:3, 3])) + float(self.robot.length)

    # -- the SolverModel interface -----------------------------------------------------------------------------

    def tip_and_jacobian(self, x: Tensor) -> TipJacobian:
        """Variables (B, n + D) → tip position (B, 3) [m], rotation (B, 3, 3) (None for a position-only robot),
        J (B, 6 or 3, n + D) (module docstring), all in the arm's base frame."""
        k = self.kinematics(x, with_base=False)
        return TipJacobian(k.position, k.rotation, k.jacobian)

    def kinematics(self, x: Tensor, with_base: bool = True) -> WholeBody:
        """Tip, Jacobian and robot base of variables (B, n + D) in one pass (:class:`WholeBody`; its
        ``base_jacobian`` None unless ``with_base``)."""
        n = self.num_arm
        theta, xc = x[:, :n], x[:, n:]
        jac_a, flange = self.arm.chain.jacobian_tensor(theta, ret_eef_pose=True)
        pc, rc, jac_c = self.robot.tip_and_jacobian(xc)
        base = flange @ self.mount
        rb, pb = base[:, :3, :3], base[:, :3, 3]
        pos = pb + (rb @ pc.unsqueeze(-1)).squeeze(-1)
        omega = jac_a[:, 3:]                                                        # (B, 3, n)
        shift = lambda point: torch.linalg.cross(omega, (point - flange[:, :3, 3]).unsqueeze(-1).expand_as(omega),  # noqa: E731
                                                 dim=1)
        arm_v = jac_a[:, :3] + shift(pos)                                           # v_i + ω_i × (p − p_a)
        linear = torch.cat([arm_v, rb @ jac_c[:, :3]], dim=-1)
        base_v = (torch.cat([jac_a[:, :3] + shift(pb), torch.zeros_like(jac_c[:, :3])], dim=-1)
                  if with_base else None)
        if rc is None:
            return WholeBody(pos, None, linear, base, base_v)
        angular = torch.cat([omega, rb @ jac_c[:, 3:]], dim=-1)
        return WholeBody(pos, rb @ rc, torch.cat([linear, angular], dim=1), base, base_v)

    def joints(self, x: Tensor) -> Tensor:
        return torch.cat([x[:, :self.num_arm], self.robot.joints(x[:, self.num_arm:])], dim=-1)

    def variables(self, q: Tensor) -> Tensor:
        q = q.to(F64)
        return torch.cat([q[:, :self.num_arm], self.robot.variables(q[:, self.num_arm:])], dim=-1)

    def check(self, q: Tensor) -> Check:
        """From the joints alone: the arm's FK (pytorch-kinematics, not the Jacobian path) and URDF limits, the
        robot's own check (its FK, limits, constraint), composed through the mount."""
        q = q.to(F64)
        theta = q[:, :self.num_arm]
        base = self.arm.tip_pose(theta) @ self.mount
        inner = self.robot.check(q[:, self.num_arm:])
        pos = base[:, :3, 3] + (base[:, :3, :3] @ inner.position.unsqueeze(-1)).squeeze(-1)
        rot = None if inner.rotation is None else base[:, :3, :3] @ inner.rotation
        inside = self.arm.limits.inside(theta) & inner.inside
        return Check(pos, rot, inside, inner.constraint)

    def seeds(self, target: Tensor, count: int) -> Tensor:
        """IK starts (B, count, n + D) for targets (B, 4, 4) or (B, 3): the admissible samples of nearest tip
        (:class:`~.seeds.PoseBank` of :data:`BANK_SIZE` samples, built on first use, fixed seed)."""
        if self._bank is None:
            self._bank = PoseBank(self, BANK_SIZE)
        return self._bank.seeds(target, count)

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The robot's body (its model's :meth:`~dacr_learn.ik.SolverModel.body`) in the arm's base frame, at
        variables x (B, n + D); differentiable in x."""
        return transform_body(self.robot.body(x[:, self.num_arm:], points_per_segment),
                              self.base_pose(x[:, :self.num_arm]))

    def links(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """The arm's link capsules (:mod:`.geometry`) at variables x (B, n + D), in the arm's base frame."""
        geometry = self.arm.geometry
        if geometry is None or geometry.radius.numel() == 0:
            return None
        a, b = posed_capsules(geometry, self.arm.frames(x[:, :self.num_arm]))
        return a, b, geometry.radius, geometry.near_mount

    def body_and_links(self, x: Tensor, points_per_segment: int = 16):
        """(:meth:`body`, :meth:`links`) at variables x (B, n + D) from one pass of the arm's forward kinematics."""
        geometry = self.arm.geometry
        frames = self.arm.frames(x[:, :self.num_arm])
        base = frames[:, self.arm.frame_names.index(self.arm.tip)] @ self.mount
        body = transform_body(self.robot.body(x[:, self.num_arm:], points_per_segment), base)
        if geometry is None or geometry.radius.numel() == 0:
            return body, None
        return body, (*posed_capsules(geometry, frames), geometry.radius, geometry.near_mount)

    # -- differentiable forward kinematics ---------------------------------------------------------------------

    def base_pose(self, theta: Tensor) -> Tensor:
        """The robot base in the world: arm joints θ (B, n) → T_a(θ)·M (B, 4, 4) [m] (differentiable)."""
        return self.arm.tip_pose(theta) @ self.mount

    def pose_of_variables(self, x: Tensor) -> Tensor:
        """Whole-body tip pose (B, 4, 4) [m] of variables (B, n + D), differentiable by autograd / torch.func:
        T_a(θ)·M·T_c(x_c) with the robot's own FK (the analytic CC model or the network; a position-only robot
        has no pose: ValueError)."""
        theta, xc = x[:, :self.num_arm], x[:, self.num_arm:]
        return self.base_pose(theta) @ robot_pose(self.robot, xc)

    def forward_kinematics(self, q: Tensor) -> Tensor:
        """Whole-body tip pose (B, 4, 4) [m] of joint vectors q (B, n + N) (θ [rad, m], the robot's joints),
        differentiable."""
        return self.pose_of_variables(self.variables(q))


def robot_pose(robot: SolverModel, x: Tensor) -> Tensor:
    """The continuum robot's tip pose (B, 4, 4) in its base frame from its variables (B, D), differentiable:
    the analytic CC FK of :class:`ConstantCurvature`, the network of :class:`LearnedFK`."""
    if isinstance(robot, ConstantCurvature):
        return forward_kinematics(robot.spec, robot.features(x))
    if isinstance(robot, LearnedFK):
        return robot.model(robot.joints(x))
    raise ValueError(f"robot: a differentiable pose needs the analytic CC model or a learned FK, got "
                     f"{type(robot).__name__} (its tip and Jacobian are still available: tip_and_jacobian)")
