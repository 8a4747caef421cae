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

x' = x + s·z, projected (:meth:`Limits.project`) only where the solver's round-off left a limit. Float64,
NumPy and DAQP (its own API, or qpsolvers for any backend) for the program, torch for the model (or its exported
evaluation, :class:`Sensing`). Pure Python; no Lightning, no Rerun.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

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
    """One step's program in scaled steps z (D,): objective ½zᵀHz + gᵀz, rows G z ≤ h, bounds lb ≤ z ≤ ub,
    and which rows are clearance dampers (``damper`` (rows,) bool)."""

    H: np.ndarray
    g: np.ndarray
    G: np.ndarray
    h: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    damper: np.ndarray


def disk_rows(pairs: np.ndarray, radius: np.ndarray, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """Half-planes n_k·(y + Δy) ≤ r·cos(π/K) of the K-gon inscribed in each disk ‖y‖ ≤ r with a vertex on the
    direction of y: pairs y (m, 2), radii r (m,) → (normals (m, K, 2), room (m, K) = r·cos(π/K) − n_k·y,
    ≥ 0 for ‖y‖ ≤ r). The normals are the K directions at angles π(2k + 1)/K turned onto y (onto x at y = 0)."""
    nx, ny, room = _disk_normals(pairs, radius, sides)
    return np.stack([nx, ny], axis=-1), room


def _disk_normals(pairs: np.ndarray, radius: np.ndarray, sides: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`disk_rows` as (n_x (m, K), n_y (m, K), room (m, K)), in few NumPy calls (it runs every step)."""
    cos, sin = _polygon(sides)
    norm = np.hypot(pairs[:, 0], pairs[:, 1])
    if (norm <= 1e-15 * radius).any():                                    # no direction: take x
        pairs, norm = pairs.copy(), norm.copy()
        small = norm <= 1e-15 * radius
        pairs[small], norm[small] = (1e-300, 0.0), 1e-300
    c, sn = (pairs / norm[:, None]).T[:, :, None]
    room = radius[:, None] * math.cos(math.pi / sides) - norm[:, None] * cos      # n_k·y = ‖y‖·cos(offset_k)
    np.maximum(room, 0.0, out=room)
    return c * cos - sn * sin, sn * cos + c * sin, room


@functools.lru_cache(maxsize=8)
def _polygon(sides: int) -> tuple[np.ndarray, np.ndarray]:
    offset = math.pi / sides * (2 * np.arange(sides) + 1)
    return np.cos(offset), np.sin(offset)


def _daqp(H, g, G, h, lb, ub) -> np.ndarray | None:
    """DAQP through its own Python API: bounds as its simple bounds, rows G z ≤ h."""
    import daqp
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
            for those not given (e.g. the AOTInductor package of :class:`Sensing`, for a kHz loop at batch 1).
        scene: the obstacles (a :class:`~dacr_learn.scene.Scene`, a scene YAML path or its dict), instead of
            ``distances``: the clearances of the model's body (``points_per_segment`` points per segment) to every
            obstacle, with their Jacobians (:mod:`.qp_clearance`); the model needs a body.

    :meth:`step`: joint vectors q (B, N), targets (B, 4, 4) poses or (B, 3) positions [m], optional feedforward
    (B, 6) (Δp [m], Δφ [rad]) or (B, 3) → q' (B, N). After a step, ``status`` holds each sample's
    :func:`solve_program` status and ``active`` the number of rows the step met with equality (bounds included).
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
        self.lower, self.upper = self.limits.lower.numpy(), self.limits.upper.numpy()
        self.disks, self.radius = self.limits.disks.numpy(), self.limits.radius.numpy()
        d = self.limits.num_variables
        self.step_bound = np.full(d, config.max_step)                        # |z_i| per step (arm: velocity too)
        self.damping_matrix = config.damping**2 * np.eye(d)
        k = config.disk_sides
        self.disk_index = (np.arange(len(self.disks) * k), self.disks[:, 0].repeat(k), self.disks[:, 1].repeat(k))
        self.disk_scale = (self.scale[self.disks[:, 0], None], self.scale[self.disks[:, 1], None])     # (m, 1)
        self.lower_scaled, self.upper_scaled = self.lower / self.scale, self.upper / self.scale
        robot = getattr(model, "robot", model)
        self.weight = float(robot.length) if config.rotation_length is None else config.rotation_length
        self.decoder = self.rate_matrix = None
        if config.joint_step is not None:
            if getattr(robot, "spec", None) is None or getattr(robot, "space", None) is None:
                raise ValueError(f"joint_step: needs a model whose variables are Clarke features of a robot file, "
                                 f"got {type(robot).__name__}")
            self.decoder = DecoderJacobian(robot.spec)
            space = robot.space
            self.rate_matrix = space.dec_matrix.numpy() if space.linear else None   # constant without twist
        self.disk_block = np.zeros((len(self.disks) * k, d))                 # refilled each step (fixed pattern)
        self.rate_rows = None if self.rate_matrix is None else self.speed_rows(np.zeros(d))
        self.status: list[str] = []
        self.solved: list[tuple[Program, np.ndarray]] = []                  # the last step's programs and steps
        self.inside_box = (self.lower - 1e-12 * self.scale, self.upper + 1e-12 * self.scale)

    # -- evaluation --------------------------------------------------------------------------------------------

    def tip_and_body(self, x: Tensor) -> tuple[TipJacobian, BodyPoints, Tensor]:
        """Tip, body and ∂p/∂x (B, P, 3, D) at x (B, D) (:func:`.qp_clearance.tip_and_body`)."""
        return tip_and_body(self.model, x, self.points_per_segment)

    def sense(self, x: Tensor) -> Sensed:
        """The model (or the ``sense`` given) at x (B, D), with the clearances when there are obstacles."""
        if self.custom_sense is not None:
            out = self.custom_sense(x)
            return out if isinstance(out, Sensed) else Sensed(*(None if t.numel() == 0 else t for t in out))
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

    def extra_rows(self, x: np.ndarray, s: Sensed, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Further rows G z ≤ h of sample b (none here; the arm adds its port)."""
        return np.zeros((0, len(x))), np.zeros(0)

    def joint_rate(self, x: np.ndarray) -> np.ndarray:
        """∂q/∂x (N, D) of the robot's joints at variables x (D,) (the Clarke decoder's Jacobian)."""
        if self.rate_matrix is not None:
            return self.rate_matrix
        return self.decoder(torch.from_numpy(x)[None])[0].numpy()

    def speed_rows(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joint-speed rows ±(∂q/∂x·s) z ≤ joint_step at variables x (D,): (2N, D), (2N,)."""
        rate = self.joint_rate(x) * self.scale
        return np.concatenate([rate, -rate]), np.full(2 * len(rate), self.config.joint_step)

    def program(self, x: np.ndarray, jac: np.ndarray, err: np.ndarray, s: Sensed, b: int) -> Program:
        """The program of one sample: variables x (D,), task rows J (k, D) and e (k,) (module docstring)."""
        cfg, scale = self.config, self.scale
        js = jac * scale
        H = js.T @ js
        H += self.damping_matrix
        g = js.T @ err
        np.negative(g, out=g)
        xs = x / scale
        lb, ub = self.lower_scaled - xs, self.upper_scaled - xs
        np.minimum(np.maximum(lb, -self.step_bound, out=lb), 0.0, out=lb)
        np.maximum(np.minimum(ub, self.step_bound, out=ub), 0.0, out=ub)
        rows, room = [], []
        if len(self.disks):
            nx, ny, free = _disk_normals(x[self.disks], self.radius, cfg.disk_sides)
            block = self.disk_block
            row, first, second = self.disk_index
            block[row, first] = (nx * self.disk_scale[0]).ravel()
            block[row, second] = (ny * self.disk_scale[1]).ravel()
            rows.append(block)
            room.append(free.ravel())
        if self.decoder is not None:
            speed, speed_room = self.speed_rows(x) if self.rate_rows is None else self.rate_rows
            rows.append(speed)
            room.append(speed_room)
        extra_g, extra_h = self.extra_rows(x, s, b)
        if len(extra_h):
            rows.append(extra_g)
            room.append(extra_h)
        fixed = sum(len(r) for r in room)
        if s.distance is not None:
            d = s.distance[b].numpy()
            near = np.flatnonzero(d < cfg.influence)
            if len(near):
                rows.append(s.distance_jacobian[b].numpy()[near] * -scale)
                room.append((d[near] - cfg.safety) * (cfg.damper_gain / (cfg.influence - cfg.safety)))
        G, h = (np.concatenate(rows), np.concatenate(room)) if rows else (np.zeros((0, len(x))), np.zeros(0))
        damper = np.zeros(len(h), dtype=bool)
        damper[fixed:] = True
        return Program(H, g, G, h, lb, ub, damper)

    def step_variables(self, x: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        """One step in variables: x (B, D) → x' (B, D), inside the limits."""
        x = x.to(F64)
        if x.dim() != 2 or x.shape[1] != self.limits.num_variables:
            raise ValueError(f"x: expected (B, {self.limits.num_variables}) variables, got {tuple(x.shape)}")
        s = self.sense(x)
        jac, err = self.task(s, target, feedforward)
        xs, jac, err = x.numpy(), jac.numpy(), err.numpy()
        out = np.empty_like(xs)
        self.status, self.solved = [], []
        for b in range(len(xs)):
            p = self.program(xs[b], jac[b], err[b], s, b)
            z, status = solve_program(p, self.config.solver, self.config.direct)
            self.solved.append((p, z))
            self.status.append(status)
            out[b] = xs[b] + self.scale * z
        out = torch.from_numpy(out)
        return self.limits.project(out) if self.outside(out) else out

    @property
    def active(self) -> list[int]:
        """Per sample of the last step, the number of rows its step met with equality (bounds included)."""
        return [int(np.count_nonzero(p.G @ z >= p.h - 1e-9) + np.count_nonzero((z <= p.lb + 1e-9) | (z >= p.ub - 1e-9)))
                for p, z in self.solved]

    def outside(self, x: Tensor) -> bool:
        """Whether some variable of x (B, D) lies outside a box or disk by more than 1e-12 of its scale (the
        solver's round-off): then :meth:`Limits.project` removes it."""
        v = x.numpy()
        lower, upper = self.inside_box
        if (v < lower).any() or (v > upper).any():
            return True
        return bool(len(self.disks)) and bool((np.hypot(v[:, self.disks[:, 0]], v[:, self.disks[:, 1]])
                                                > self.radius * (1 + 1e-12)).any())

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        """One step in joints: q (B, N) → q' (B, N) (module docstring)."""
        x = self.model.variables(q.to(F64))
        return self.model.joints(self.step_variables(x, target, feedforward))


class Sensing(nn.Module):
    """A controller's evaluation of its model and clearances as a module, for torch.export / AOTInductor:
    x (B, D) → the seven fields of :class:`Sensed`, empty (B, 0) tensors for those it does not give. The loaded
    package is the controller's ``sense`` (the program itself stays in NumPy/qpsolvers)."""

    def __init__(self, controller: QPController):
        super().__init__()
        self.controller = controller

    def forward(self, x: Tensor) -> tuple[Tensor, ...]:
        empty = x[:, :0]
        return tuple(empty if t is None else t for t in self.controller.sense(x))
