"""Constrained resolved-rate control: one quadratic program per control step (DAQP, directly or via qpsolvers).

For any IK model (:class:`~dacr_learn.ik.SolverModel`: the Clarke features of a robot, a learned FK, a hardware
model; the arm composite in :mod:`dacr_learn.arm.qp_control`) with variables x (D,), limits and scales s
(:class:`~dacr_learn.ik.Limits`), one step solves, in scaled steps z = Δx/s,

    min_z  ½‖J̃z − e‖² + ½λ²‖z‖²                 J̃ = W·J·diag(s), e = W·(gain·error + feedforward)
    s.t.   lower ≤ x + s·z ≤ upper,  |z_i| ≤ max_step                      (joint boxes, step = velocity·dt)
           n_k·(ρ + Δρ) ≤ r·cos(π/K), k < K                                 (each Clarke bend disk ‖ρ‖ ≤ r)
           |∂q/∂x·s·z| ≤ joint_step                                         (the robot's joint speeds, optional)
           ∂d_j/∂x·s·z ≥ −ξ·(d_j − d_s)/(d_i − d_s)  for every d_j < d_i     (velocity dampers on clearances)

with e and J the tip error and Jacobian (position rows, and w·rotation rows for a pose target, w =
``rotation_length`` [m/rad]), λ = ``damping``. Without an active constraint the solution is the damped
least-squares step of :func:`~dacr_learn.deploy.control.scaled_dls_step`, z = J̃ᵀ(J̃J̃ᵀ + λ²I)⁻¹e.

- **Bend disk**: the regular K-gon inscribed in the disk with a vertex on the current direction of ρ (so the
  current point is feasible and the limit is exact along that direction); the polygon lies inside the disk, so
  a step never leaves it.
- **Clearance**: a ``scene`` (the model's body to its obstacles, the scene's closed-form distance gradients times
  the body's Jacobian: :mod:`.qp_clearance`) or any ``distances(x) → (d (B, M) [m], ∂d/∂x (B, M, D) [m per
  variable unit])``: signed distances of body points to obstacles (negative: penetration) and their Jacobians.
  d_s = ``safety``, d_i =
  ``influence``, ξ = ``damper_gain`` [m per step]: d may shrink by at most the fraction ξ/(d_i − d_s) of its
  margin d − d_s per step, so it approaches d_s but (to first order) never crosses it.
- A clearance already below d_s asks to move away; when that cannot be met the program is solved again with
  those rows relaxed to "do not come closer" (``status`` "relaxed"), and a step of zero is taken if even that
  fails ("held"). Zero always satisfies every other row, so the step is always inside the limits.

x' = x + s·z, projected (:meth:`Limits.project`) only where the solver's round-off left a limit. The program's
matrices are built in torch, batched (:meth:`QPController.program_rows`: every clearance a row, those at or beyond
d_i marked to be left out), so that the whole step up to the solve exports as one module (:mod:`.qp_export`);
each sample's program is then solved by DAQP (its own API, or qpsolvers for any backend). Float64; pure Python,
no Lightning, no Rerun.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import daqp
import numpy as np
import qpsolvers
import torch
from torch import Tensor, nn

from ..body import BodyPoints, check_points_per_segment
from ..checks import F64
from ..clarke_space import DecoderJacobian
from ..ik.adapters import SolverModel, TipJacobian
from ..scene import load_scene
from .control import ControllerConfig, tip_task
from .qp_clearance import SceneLike, clearance_rows, tip_and_body

DistanceFn = Callable[[Tensor], tuple[Tensor, Tensor]]
"""x (B, D) → (d (B, M) [m], ∂d/∂x (B, M, D)): clearances of the body to the obstacles and their Jacobians."""


@dataclass(frozen=True)
class QPConfig(ControllerConfig):
    """Gains, limits and clearance of :class:`QPController` (module docstring).

    gain: fraction of the tip error corrected per step, (0, 1] (:class:`~.control.ControllerConfig`);
    damping: λ > 0 [m]; max_step: largest |Δx_i|/s_i per step (the variables' velocity limit × dt, in scaled
    units); rotation_length: w [m/rad] for a pose target (None: the robot's length); joint_step: largest |Δq| of
    the robot's joints per step [m, rad] (None: not applied); safety d_s ≥ 0 [m] and influence d_i > d_s [m] of
    the dampers, damper_gain ξ > 0 [m per step]; disk_sides K ≥ 3 of the bend-disk polygon; solver: a qpsolvers
    backend ("daqp", "proxqp", …); direct: call "daqp" through its own Python API (False: through qpsolvers).
    """

    damping: float = 1e-3
    rotation_length: float | None = None
    joint_step: float | None = None
    safety: float = 0.002
    influence: float = 0.02
    damper_gain: float = 0.002
    disk_sides: int = 8
    solver: str = "daqp"
    direct: bool = True

    def __post_init__(self):
        super().__post_init__()
        checks = [("damping", self.damping is not None and self.damping > 0, "> 0 [m]"),
                  ("rotation_length", self.rotation_length is None or self.rotation_length > 0, "> 0 [m/rad]"),
                  ("joint_step", self.joint_step is None or self.joint_step > 0, "> 0 [m, rad per step]"),
                  ("safety", self.safety >= 0, ">= 0 [m]"),
                  ("influence", self.influence > self.safety, f"> safety ({self.safety} m)"),
                  ("damper_gain", self.damper_gain > 0, "> 0 [m per step]"),
                  ("disk_sides", isinstance(self.disk_sides, int) and self.disk_sides >= 3, "an integer >= 3")]
        for name, ok, expected in checks:
            if not ok:
                raise ValueError(f"{name}: expected {expected}, got {getattr(self, name)!r}")
        if self.solver not in qpsolvers.available_solvers:
            raise ValueError(f"solver: expected one of the installed qpsolvers backends "
                             f"{sorted(qpsolvers.available_solvers)}, got {self.solver!r}")


class Sensed(NamedTuple):
    """What one step needs of the model at x (B, D): tip ``position`` (B, 3) [m], ``rotation`` (B, 3, 3) or None,
    ``jacobian`` (B, 6 or 3, D), clearances ``distance`` (B, M) [m] and ``distance_jacobian`` (B, M, D) or None,
    and for an arm composite the robot's ``base`` point (B, 3) [m] and its Jacobian (B, 3, D), else None."""

    position: Tensor
    rotation: Tensor | None
    jacobian: Tensor
    distance: Tensor | None = None
    distance_jacobian: Tensor | None = None
    base: Tensor | None = None
    base_jacobian: Tensor | None = None


class Program(NamedTuple):
    """One sample's program in scaled steps z (D,): objective ½zᵀHz + gᵀz, rows G z ≤ h, bounds lb ≤ z ≤ ub,
    and which rows are clearance dampers (``damper`` (rows,) bool)."""

    H: np.ndarray
    g: np.ndarray
    G: np.ndarray
    h: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    damper: np.ndarray


class Rows(NamedTuple):
    """A batch's programs as tensors, with a fixed number R of rows: H (B, D, D), g (B, D), G (B, R, D), h (B, R),
    lb, ub (B, D) and ``kind`` (B, R): 1 a fixed row (bend disks, joint speeds, port), 2 a damper, 0 a
    clearance at or beyond d_i (left out of the sample's :class:`Program`); float64 like the rest."""

    H: Tensor
    g: Tensor
    G: Tensor
    h: Tensor
    lb: Tensor
    ub: Tensor
    kind: Tensor


def disk_rows(pairs: Tensor, radius: Tensor, sides: int) -> tuple[Tensor, Tensor]:
    """Half-planes n_k·(y + Δy) ≤ r·cos(π/K) of the K-gon inscribed in each disk ‖y‖ ≤ r with a vertex on the
    direction of y: pairs y (..., m, 2), radii r (m,) → (normals (..., m, K, 2), room (..., m, K) = r·cos(π/K) −
    n_k·y, ≥ 0 for ‖y‖ ≤ r). The normals are the K directions at angles π(2k + 1)/K turned onto y (onto x at
    y = 0)."""
    offset = math.pi / sides * (2 * torch.arange(sides, dtype=pairs.dtype, device=pairs.device) + 1)
    cos, sin = torch.cos(offset), torch.sin(offset)
    norm = torch.hypot(pairs[..., 0], pairs[..., 1])
    small = norm <= 1e-15 * radius                                                 # no direction: take x
    safe = torch.where(small, 1.0, norm)
    c = torch.where(small, 1.0, pairs[..., 0] / safe).unsqueeze(-1)
    sn = torch.where(small, 0.0, pairs[..., 1] / safe).unsqueeze(-1)
    room = radius.unsqueeze(-1) * math.cos(math.pi / sides) - torch.where(small, 0.0, norm).unsqueeze(-1) * cos
    return torch.stack([c * cos - sn * sin, sn * cos + c * sin], dim=-1), torch.clamp_min(room, 0.0)


def _daqp(H, g, G, h, lb, ub) -> np.ndarray | None:
    """DAQP through its own Python API: bounds as its simple bounds, rows G z ≤ h."""
    upper, lower = np.concatenate([ub, h]), np.concatenate([lb, np.full(len(h), -1e30)])
    z, _, flag, _ = daqp.solve(H, g, G, upper, lower, np.zeros(len(upper), dtype=np.intc))
    return z if flag > 0 else None


def solve_program(program: Program, solver: str, direct: bool = True) -> tuple[np.ndarray, str]:
    """The scaled step z (D,) of a program and a status: "ok"; "relaxed" (the damper rows asking to move away
    could not be met and were relaxed to "do not come closer"); "held" (no solution: z = 0). ``direct``: the
    "daqp" solver through DAQP's own API (the same solver without qpsolvers' generic conversions), else through
    :func:`qpsolvers.solve_qp`."""
    p = program
    if direct and solver == "daqp":
        solve = _daqp
    else:
        def solve(H, g, G, h, lb, ub):
            return qpsolvers.solve_qp(H, g, G if len(h) else None, h if len(h) else None, lb=lb, ub=ub,
                                      solver=solver)
    z = solve(p.H, p.g, p.G, p.h, p.lb, p.ub)
    if z is not None:
        return z, "ok"
    pushing = p.damper & (p.h < 0)
    if pushing.any():
        z = solve(p.H, p.g, p.G, np.where(pushing, 0.0, p.h), p.lb, p.ub)
        if z is not None:
            return z, "relaxed"
    return np.zeros_like(p.g), "held"


class QPController:
    """Constrained resolved-rate control of a model's tip (module docstring).

    Args:
        model: the model to control (a :class:`~dacr_learn.ik.SolverModel`, e.g. ``ConstantCurvature(spec)``).
        config: :class:`QPConfig`. distances: the clearance provider (:data:`DistanceFn`), or None (no obstacles).
        sense: replaces the model's evaluation, x (B, D) → :class:`Sensed` or its fields as a tuple, empty tensors
            for those not given (e.g. the AOTInductor package of :class:`Sensing`).
        scene: the obstacles (a :class:`~dacr_learn.scene.Scene`, a scene YAML path or its dict), instead of
            ``distances``: the clearances of the model's body (``points_per_segment`` points per segment) to every
            obstacle, with their Jacobians (:mod:`.qp_clearance`); the model needs a body.

    :meth:`step`: joint vectors q (B, N), targets (B, 4, 4) poses or (B, 3) positions [m], optional feedforward
    (B, 6) (Δp [m], Δφ [rad]) or (B, 3) → q' (B, N) (:class:`~.qp_export.ExportedStep`: the same step through an
    AOTInductor package). After a step, ``status`` holds each sample's :func:`solve_program` status and
    ``active`` the number of rows the step met with equality (bounds included).
    """

    def __init__(self, model: SolverModel, config: QPConfig = QPConfig(), distances: DistanceFn | None = None,
                 sense: Callable[[Tensor], Sensed | tuple] | None = None, scene: SceneLike | None = None,
                 points_per_segment: int = 8):
        if scene is not None and distances is not None:
            raise ValueError("scene, distances: expected one clearance provider, got both")
        self.model, self.config, self.distances, self.custom_sense = model, config, distances, sense
        self.scene, self.points_per_segment = None, check_points_per_segment(points_per_segment)
        if scene is not None:
            self.scene = load_scene(scene)
            model.body(model.rest[None], points_per_segment)                 # a model without a body: ValueError
        self.limits = model.limits.to(F64)
        self.scale = self.limits.scale.numpy()
        self.disks = self.limits.disks
        d = self.limits.num_variables
        self.step_bound = torch.full((d,), float(config.max_step), dtype=F64)      # |z_i| (arm: velocity too)
        self.damping_matrix = config.damping**2 * torch.eye(d, dtype=F64)
        lim = self.limits
        self.lower_scaled, self.upper_scaled = lim.lower / lim.scale, lim.upper / lim.scale
        eye = torch.eye(d, dtype=F64) * self.limits.scale                            # column i: e_i·s_i
        self.disk_place = (eye[self.disks[:, 0]], eye[self.disks[:, 1]])             # (m, D) each
        robot = getattr(model, "robot", model)
        self.weight = float(robot.length) if config.rotation_length is None else config.rotation_length
        self.decoder = self.rate_matrix = None
        if config.joint_step is not None:
            if getattr(robot, "spec", None) is None or getattr(robot, "space", None) is None:
                raise ValueError(f"joint_step: needs a model whose variables are Clarke features of a robot file, "
                                 f"got {type(robot).__name__}")
            self.decoder = DecoderJacobian(robot.spec)
            space = robot.space
            self.rate_matrix = space.dec_matrix.to(F64).clone() if space.linear else None  # constant without twist
        self.status: list[str] = []
        self.solved: list[tuple[Program, np.ndarray]] = []                  # the last step's programs and steps
        tol = 1e-12 * lim.scale
        self.inside_box = ((lim.lower - tol).numpy(), (lim.upper + tol).numpy())         # the round-off allowed
        self.disk_columns = (self.disks[:, 0].numpy(), self.disks[:, 1].numpy(), (lim.radius * (1 + 1e-12)).numpy())

    # -- evaluation --------------------------------------------------------------------------------------------

    def tip_and_body(self, x: Tensor) -> tuple[TipJacobian, BodyPoints, Tensor]:
        """Tip, body and ∂p/∂x (B, P, 3, D) at x (B, D) (:func:`.qp_clearance.tip_and_body`)."""
        return tip_and_body(self.model, x, self.points_per_segment)

    def sense(self, x: Tensor) -> Sensed:
        """The ``sense`` given, else :meth:`evaluate`, at x (B, D)."""
        if self.custom_sense is None:
            return self.evaluate(x)
        out = self.custom_sense(x)
        return out if isinstance(out, Sensed) else Sensed(*(None if t.numel() == 0 else t for t in out))

    def evaluate(self, x: Tensor) -> Sensed:
        """The model at x (B, D), with the clearances when there are obstacles."""
        if self.scene is not None:
            tip, body, jac_p = self.tip_and_body(x)
            return Sensed(*tip, *clearance_rows(self.scene, body, jac_p))
        position, rotation, jac = self.model.tip_and_jacobian(x)
        d, jd = (None, None) if self.distances is None else self.distances(x)
        return Sensed(position, rotation, jac, d, jd)

    def task(self, s: Sensed, target: Tensor, feedforward: Tensor | None) -> tuple[Tensor, Tensor]:
        """Weighted task rows: (J (B, k, D), e (B, k)) — position rows, and w·rotation rows for a pose target."""
        rows, err = tip_task(s.jacobian, s.position, s.rotation, target, feedforward, self.config.gain, self.weight)
        return torch.cat(rows, dim=1), torch.cat(err, dim=-1)

    # -- the program -------------------------------------------------------------------------------------------

    def extra_rows(self, x: Tensor, s: Sensed) -> tuple[Tensor, Tensor] | None:
        """Further rows G z ≤ h at x (B, D): (B, r, D), (B, r), or None (none here; the arm adds its port)."""
        return None

    def joint_rate(self, x: Tensor) -> Tensor:
        """∂q/∂x (N, D), or (B, N, D) where it varies, of the robot's joints at variables x (B, D)."""
        return self.rate_matrix if self.rate_matrix is not None else self.decoder(x)

    def program_rows(self, x: Tensor, s: Sensed, jac: Tensor, err: Tensor) -> Rows:
        """The programs of a batch (module docstring): variables x (B, D), the model's evaluation, task rows
        J (B, k, D) and e (B, k) → :class:`Rows`; rows in the order bend disks, joint speeds, extra, dampers."""
        cfg, scale, (b, d) = self.config, self.limits.scale, x.shape
        js = jac * scale
        H = js.mT @ js + self.damping_matrix
        g = -(js.mT @ err.unsqueeze(-1)).squeeze(-1)
        xs = x / scale
        lb = torch.clamp(torch.maximum(self.lower_scaled - xs, -self.step_bound), max=0.0)
        ub = torch.clamp(torch.minimum(self.upper_scaled - xs, self.step_bound), min=0.0)
        rows, room = [], []
        if len(self.disks):
            normals, free = disk_rows(x[:, self.disks], self.limits.radius, cfg.disk_sides)   # (B, m, K, 2), (B, m, K)
            place0, place1 = (p.unsqueeze(1) for p in self.disk_place)                       # (m, 1, D)
            rows.append((normals[..., :1] * place0 + normals[..., 1:] * place1).flatten(1, 2))
            room.append(free.flatten(1))
        if self.decoder is not None:
            rate = self.joint_rate(x) * scale
            rows.append(torch.cat([rate, -rate], dim=-2).expand(b, -1, -1))
            room.append(x.new_full((b, 2 * rate.shape[-2]), self.config.joint_step))
        extra = self.extra_rows(x, s)
        if extra is not None:
            rows.append(extra[0])
            room.append(extra[1])
        kind = [x.new_ones(b, sum(r.shape[1] for r in room))]            # float: an int cat would not compile inline
        if s.distance is not None:
            rows.append(s.distance_jacobian * -scale)
            room.append((s.distance - cfg.safety) * (cfg.damper_gain / (cfg.influence - cfg.safety)))
            kind.append(2.0 * (s.distance < cfg.influence).to(x.dtype))
        G = torch.cat(rows, dim=1) if rows else x.new_zeros(b, 0, d)
        h = torch.cat(room, dim=1) if room else x.new_zeros(b, 0)
        return Rows(H, g, G, h, lb, ub, torch.cat(kind, dim=1))

    def programs(self, rows: Rows) -> list[Program]:
        """Each sample's :class:`Program` of a batch's rows (the clearances marked 0 left out)."""
        H, g, G, h, lb, ub, kind = (t.numpy() for t in rows)
        out = []
        for b in range(len(g)):
            keep = np.flatnonzero(kind[b])
            out.append(Program(H[b], g[b], G[b][keep], h[b][keep], lb[b], ub[b], kind[b][keep] == 2))
        return out

    def solve_rows(self, x: Tensor, rows: Rows) -> Tensor:
        """Solve each sample's program: x (B, D) and its :class:`Rows` → x' = x + s·z (B, D), inside the limits."""
        xs, cfg = x.numpy(), self.config
        out = np.empty_like(xs)
        self.status, self.solved = [], []
        for b, p in enumerate(self.programs(rows)):
            z, status = solve_program(p, cfg.solver, cfg.direct)
            self.solved.append((p, z))
            self.status.append(status)
            out[b] = xs[b] + self.scale * z
        outside = self.outside(out)
        out = torch.from_numpy(out)
        return self.limits.project(out) if outside else out

    def step_variables(self, x: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        """One step in variables, eager: x (B, D) → x' (B, D), inside the limits."""
        x = x.to(F64)
        if x.dim() != 2 or x.shape[1] != self.limits.num_variables:
            raise ValueError(f"x: expected (B, {self.limits.num_variables}) variables, got {tuple(x.shape)}")
        s = self.sense(x)
        jac, err = self.task(s, target, feedforward)
        return self.solve_rows(x, self.program_rows(x, s, jac, err))

    @property
    def active(self) -> list[int]:
        """Per sample of the last step, the number of rows its step met with equality (bounds included)."""
        return [int(np.count_nonzero(p.G @ z >= p.h - 1e-9) + np.count_nonzero((z <= p.lb + 1e-9) | (z >= p.ub - 1e-9)))
                for p, z in self.solved]

    def outside(self, x: Tensor | np.ndarray) -> bool:
        """Whether some variable of x (B, D) lies outside a box or disk by more than 1e-12 of its scale (the
        solver's round-off): then :meth:`Limits.project` removes it."""
        v = x.numpy() if isinstance(x, Tensor) else x
        lower, upper = self.inside_box
        if (v < lower).any() or (v > upper).any():
            return True
        first, second, rim = self.disk_columns
        return len(rim) > 0 and bool((np.hypot(v[:, first], v[:, second]) > rim).any())

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        """One step in joints: q (B, N) → q' (B, N) (module docstring)."""
        x = self.model.variables(q.to(F64))
        return self.model.joints(self.step_variables(x, target, feedforward))


class Sensing(nn.Module):
    """A controller's evaluation of its model and clearances as a module, for torch.export / AOTInductor:
    x (B, D) → the seven fields of :class:`Sensed`, empty (B, 0) tensors for those it does not give; the loaded
    package can be a controller's ``sense`` (:class:`~.qp_export.StepProgram` exports the program rows too)."""

    def __init__(self, controller: QPController):
        super().__init__()
        self.controller = controller

    def forward(self, x: Tensor) -> tuple[Tensor, ...]:
        empty = x[:, :0]
        return tuple(empty if t is None else t for t in self.controller.evaluate(x))
