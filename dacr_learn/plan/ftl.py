"""Follow-the-leader planning: the insertion of a (possibly arm-mounted) continuum robot along a path.

:func:`plan_ftl` returns T configurations whose tip advances along the path from its start, arc length s from 0
to min(path length, L), while the inserted body stays on the traversed path (docs/plan.md):

1. **first step** (s = 0): the multi-solution IK solver (:func:`dacr_learn.ik.solve_ik`, seeded by the arm's
   pose bank) puts the tip on the path's start pointing along the path, at several rolls; each solution is
   refined on the step problem (:mod:`.solve`: the whole body on the entry line, every point weighing alike)
   and the lowest cost is kept (of equal ones, the arm's best-conditioned configuration);
2. **continuation**: each of the T steps refined from the previous one (Levenberg–Marquardt on tip + body
   residuals, limits inside the step, a weak pull towards the previous step) and its tip polished onto the path;
   a step that misses the path or changes a variable by more than its bound is taken in halves (at most
   :attr:`FTLOptions.substeps` halvings, where the path turns fast), then **recovered** from the IK solver's
   solutions nearest the previous step;
3. **verdict**: from the joints alone (the model's own check): every tip within ``tolerance``·L of its path
   point, inside every limit, and no variable changing by more than :meth:`FTLOptions.bounds` between
   consecutive steps; with a scene, also the clearance of the body (and an arm's links) to the obstacles ≥ D
   at every step (:meth:`dacr_learn.ik.collision.Avoidance.clearance_of_joints`, solve_ik's own check); else
   ``success`` False and ``reason`` names the first failure. With a scene, every step's least squares also
   carries clearance hinges (:mod:`.solve`): the body avoids the obstacles as it follows the path.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from ..arm import Composite
from ..arm.chain import CONTINUOUS_RANGE
from ..arm.seeds import PoseBank
from ..checks import F64
from ..ik import IKOptions, solve_ik
from ..ik.adapters import SolverModel, as_solver_model
from ..ik.collision import Avoidance
from ..scene import load_scene
from .body import body
from .metric import shape_deviation
from .path import Path
from .solve import Problem, StepOptions

BANK_SIZE = 2048   # admissible samples seeding the IK of the first step and of a recovery (dacr_learn.arm.seeds)
ROLLS = 4          # rolls about the path's entry direction tried for the first step
FIRST_ITERATIONS = 40   # LM steps of the first step (from IK solutions: the body may start far from the line)
CLEAR_TRIES = 5    # refinements of a step whose clearance falls below D (hinges lifted, 3× as stiff each)
TIE = 1e-10         # step costs (units of L²) this close count as equally good for the first step


@dataclass(frozen=True)
class FTLOptions:
    """tolerance: tip error allowed, relative to the robot's length L; spacing: default step spacing along the
    path, relative to L; iterations: LM steps per step; substeps: halvings of a step that misses the path or
    jumps; max_change: the continuity bound per step of the default spacing (proportional to the step's arc
    length), in rad for revolute arm joints and twists, in units of L for prismatic ones and segment lengths,
    in units of the variable's scale for the robot's others (bend ρ: of its disk radius); solutions: IK
    solutions tried for the first step and a recovery."""

    tolerance: float = 1e-6
    spacing: float = 0.01
    iterations: int = 12
    substeps: int = 3
    max_change: float = 0.1
    solutions: int = 8
    step: StepOptions = field(default_factory=StepOptions)

    def __post_init__(self):
        for name in ("tolerance", "spacing", "max_change"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a finite value > 0, got {v}")


@dataclass
class FTLPlan:
    """A plan of T steps. q (T, N) joint vectors (an arm's joints first, then the robot's); x (T, D) the
    solver's variables; s (T,) [m] the tip's arc length along the path; tip_err (T,) [m]; shape_dev and
    shape_dev_max (T,) [m] (:mod:`.metric`); clearance (T,) [m] of the body (and an arm's links) to the scene's
    obstacles (+inf without a scene); success; reason ('' on success); length L [m]."""

    q: Tensor
    x: Tensor
    s: Tensor
    tip_err: Tensor
    shape_dev: Tensor
    shape_dev_max: Tensor
    success: bool
    reason: str
    length: float
    clearance: Tensor | None = None

    def __post_init__(self):
        if self.clearance is None:
            self.clearance = torch.full_like(self.s, float("inf"))

    def arrays(self) -> dict[str, np.ndarray]:
        """The PLAN.npz arrays (docs/plan.md)."""
        out = {k: getattr(self, k).detach().to(F64).numpy() for k in ("q", "s", "tip_err", "shape_dev",
                                                                        "shape_dev_max", "clearance")}
        out["success"] = np.array(self.success)
        out["reason"] = np.array(self.reason)
        return out


def robot_length(model: SolverModel) -> float:
    """The continuum robot's nominal length L [m] (of the robot an arm carries)."""
    return float(model.robot.length if isinstance(model, Composite) else model.length)


def _entry_frames(path: Path, rolls: int) -> Tensor:
    """Poses (rolls, 4, 4) at the path's start with z along its entry direction, rotated about it."""
    z = path.entry
    helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(z[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=F64)
    x0 = torch.linalg.cross(helper, z)
    x0 = x0 / torch.linalg.vector_norm(x0)
    y0 = torch.linalg.cross(z, x0)
    out = torch.eye(4, dtype=F64).repeat(rolls, 1, 1)
    for k in range(rolls):
        a = 2 * math.pi * k / rolls
        xr = math.cos(a) * x0 + math.sin(a) * y0
        out[k, :3, :3] = torch.stack([xr, torch.linalg.cross(z, xr), z], dim=1)
        out[k, :3, 3] = path.points[0]
    return out


class _Planner:
    def __init__(self, model: SolverModel, path: Path, options: FTLOptions, avoid: Avoidance | None = None):
        self.model, self.path, self.opts, self.avoid = model, path, options, avoid
        self.length = robot_length(model)
        self.tol = options.tolerance * self.length
        scene = () if avoid is None else (avoid.scene, avoid.clearance)
        self.problem = Problem(model, path, self.length, options.step, *scene)
        self.start = Problem(model, path, self.length, replace(options.step, outside_weight=1.0), *scene)
        self.bank = None

    def _candidates(self, targets: Tensor, position_only: bool, q0: Tensor | None = None) -> Tensor:
        """Successful IK solutions (C, D) of targets (poses (B, 4, 4) or positions (B, 3)), without restarts
        (a roll the robot cannot give its tip is not worth them: the body problem fixes the roll anyway)."""
        k = self.opts.solutions if position_only else max(1, self.opts.solutions // targets.shape[0])
        if self.bank is None and isinstance(self.model, Composite):
            self.bank = PoseBank(self.model, BANK_SIZE)
        seeds = None if self.bank is None else self.bank.seeds(targets, k)
        scene = {} if self.avoid is None else {"scene": self.avoid.scene, "clearance": self.avoid.clearance}
        res = solve_ik(self.model, targets, k, q0=q0, position_only=position_only, seeds=seeds,
                       options=IKOptions(restarts=0), **scene)
        q = res.q.reshape(-1, res.q.shape[-1])[res.success.reshape(-1)]
        return self.model.variables(q)

    def _best(self, cand: Tensor, s: float, ref: Tensor | None, iterations: int) -> tuple[Tensor, bool]:
        """The candidate (D,) of least step cost after refinement and polish (tip on the path first)."""
        sv = torch.full((cand.shape[0],), s, dtype=F64)
        problem = self.problem if ref is not None else self.start   # the first step: the whole body on the line
        x, cost, _ = problem.refine(cand, sv, cand if ref is None else ref.expand_as(cand), iterations)
        x, tip = self.problem.polish(x, sv, 1e-3 * self.tol)
        ok = tip <= self.tol
        if ref is not None:       # a recovery: prefer the solution nearest the previous step
            cost = cost + ((x - ref) / self.problem.scale).square().sum(-1) * 1e-6
        cost = torch.where(ok, cost, cost + 1e6)
        if ref is None and isinstance(self.model, Composite):   # first step: of the equally good, the arm's
            tie = cost <= cost.min() + TIE                        # best-conditioned (far from its singularities)
            jac = self.model.tip_and_jacobian(x)[2][:, :, :self.model.num_arm]
            sigma = torch.linalg.svdvals(jac)[:, -1]
            cost = torch.where(tie, -sigma, torch.full_like(sigma, float("inf")))
        i = int(cost.argmin())
        return x[i], bool(ok[i])

    def _wrapped(self, x: Tensor) -> Tensor:
        """x with the angles of continuous arm joints (box ±2π) wrapped into [−π, π): as far from their box as
        they can be."""
        if not isinstance(self.model, Composite):
            return x
        lim = self.model.arm.limits
        free = ((lim.lower <= -CONTINUOUS_RANGE) & (lim.upper >= CONTINUOUS_RANGE)).nonzero().squeeze(-1)
        x = x.clone()
        x[:, free] = torch.remainder(x[:, free] + math.pi, 2 * math.pi) - math.pi
        return x

    def first(self) -> tuple[Tensor | None, str]:
        cand = self._candidates(self.path.points[:1], True)
        if self.model.has_rotation:
            cand = torch.cat([self._candidates(_entry_frames(self.path, ROLLS), False), cand])
        if cand.shape[0] == 0:
            return None, f"the tip cannot reach the path's start {self.path.points[0].tolist()} (IK found no solution)"
        x, ok = self._best(self._wrapped(cand), 0.0, None, FIRST_ITERATIONS)
        sv = torch.zeros(1, dtype=F64)
        x = self._keep_clear(x[None], self.problem.tip_error(x[None], sv), sv, x[None])[0][0]
        ok = ok and float(self.problem.tip_error(x[None], sv)[0]) <= self.tol
        return x, "" if ok else "the tip cannot be put on the path's start inside the limits"

    def _solve(self, prev: Tensor, s0: float, s: float, clear: bool = True) -> tuple[Tensor, Tensor]:
        """The step (1, D) at tip arc length s continued from ``prev`` (1, D) at s0: LM pulled weakly towards prev
        (the conditioning term weighted by √(Δs / spacing): its drift per step ∝ Δs), then the tip polished onto
        its path point; and its tip error (1,) [m]."""
        sv = torch.tensor([s], dtype=F64)
        steer = math.sqrt(max(s - s0, 0.0) / (self.opts.spacing * self.length))
        x, _, _ = self.problem.refine(prev.clone(), sv, prev, self.opts.iterations, steer=steer)
        x, tip = self.problem.polish(x, sv, 1e-3 * self.tol)
        return self._keep_clear(x, tip, sv, prev, steer) if clear else (x, tip)

    def _keep_clear(self, x: Tensor, tip: Tensor, sv: Tensor, prev: Tensor, steer: float = 1.0):
        """With a scene: while the step's clearance (the verdict's check) is below D, refined again with the
        hinges' target lifted by twice the shortfall and their weight 3× (at most :data:`CLEAR_TRIES` times): a
        soft hinge gives way a little, and an obstacle may poke between the hinges' samples. A refinement is kept
        if it keeps the tip and raises the clearance (a step it makes jump is halved by :meth:`_advance`, or at
        last taken without it)."""
        if self.avoid is None:
            return x, tip
        clear = float(self.avoid.clearance_of_joints(self.model.joints(x))[0])
        lift, hinge = 0.0, 1.0
        for _ in range(CLEAR_TRIES):
            if clear >= self.avoid.clearance:
                break
            lift, hinge = lift + 2 * (self.avoid.clearance - clear), hinge * 3
            y, _, _ = self.problem.refine(x, sv, prev, self.opts.iterations, steer=steer, hinge=hinge, lift=lift)
            y, tip_y = self.problem.polish(y, sv, 1e-3 * self.tol)
            clear_y = float(self.avoid.clearance_of_joints(self.model.joints(y))[0])
            if float(tip_y[0]) <= self.tol and clear_y > clear:
                x, tip, clear = y, tip_y, clear_y
        return x, tip

    def _advance(self, prev: Tensor, s0: float, s1: float, depth: int = 0) -> tuple[Tensor, float]:
        """The solution (1, D) at s1 continued from ``prev`` (1, D), the solution at s0 < s1. A step that misses
        the path or changes a variable by more than its bound is taken in two halves (at most
        ``options.substeps`` halvings: the path turns fast there), then recovered from the IK solutions nearest
        ``prev``. Returns it and its tip error [m]."""
        x, tip = self._solve(prev, s0, s1)
        missed = float(tip[0]) > self.tol
        jump = float(((x - prev).abs() / self.bounds(s1 - s0)).max())
        if not missed and jump <= 1.0:
            return x, float(tip[0])
        if depth < self.opts.substeps:
            mid = 0.5 * (s0 + s1)
            return self._advance(self._advance(prev, s0, mid, depth + 1)[0], mid, s1, depth + 1)
        if not missed and self.avoid is not None:        # still a jump: the step without the clearance refinement
            y, tip_y = self._solve(prev, s0, s1, clear=False)
            if float(tip_y[0]) <= self.tol and bool(((y - prev).abs() <= self.bounds(s1 - s0)).all()):
                x, tip = y, tip_y
        if missed:                                                                      # recovery
            cand = self._candidates(self.path.at(torch.tensor([s1], dtype=F64)), True, q0=self.model.joints(prev))
            if cand.shape[0]:
                x = self._best(torch.cat([x, cand]), s1, prev[0], self.opts.iterations)[0][None]
                tip = self.problem.tip_error(x, torch.tensor([s1], dtype=F64))
        return x, float(tip[0])

    def follow(self, x0: Tensor, s: Tensor) -> tuple[Tensor, str]:
        """The steps (T, D) at tip arc lengths s (T,), each continued from the previous one; and a reason when
        the tip could not follow."""
        xs, reason = [x0[None]], ""
        for k in range(1, s.shape[0]):
            x, tip = self._advance(xs[-1], float(s[k - 1]), float(s[k]))
            if not reason and tip > self.tol:
                reason = f"the tip cannot follow the path at s = {float(s[k]):.6g} m (step {k}; no IK solution there)"
            xs.append(x)
        return torch.cat(xs), reason

    def bounds(self, ds: float) -> Tensor:
        """The largest change of each variable (D,) allowed between consecutive steps ds [m] apart."""
        factor = self.opts.max_change * ds / (self.opts.spacing * self.length)
        scale = self.problem.scale.clone()
        out = factor * scale
        names = self.model.limits.names
        for j, name in enumerate(names):     # lengths like the path's advance, twists like joint angles
            if name.endswith(".beta"):
                out[j] = factor * self.length
            elif name.endswith(".alpha"):
                out[j] = factor
        if isinstance(self.model, Composite):
            n = self.model.num_arm
            kinds = self.model.arm.joint_types
            out[:n] = torch.tensor([factor * (self.length if k == "prismatic" else 1.0) for k in kinds], dtype=F64)
        return out

    def verdict(self, x: Tensor, s: Tensor, reason: str) -> FTLPlan:
        q = self.model.joints(x)
        check = self.model.check(q)
        tip_err = torch.linalg.vector_norm(check.position - self.path.at(s), dim=-1)
        b = body(self.model, x)
        dev, dev_max = shape_deviation(b.points, b.arc, self.path, s)
        fails = []                         # (step, reason) of each criterion's first failure; the earliest wins
        if bool((tip_err > self.tol).any()):
            k = int((tip_err > self.tol).nonzero()[0])
            fails.append((k, f"tip error {float(tip_err[k]):.3g} m > tolerance {self.tol:.3g} m at step {k} "
                             f"(s = {float(s[k]):.6g} m)"))
        if not bool(check.inside.all()):
            k = int((~check.inside).nonzero()[0])
            viol = self.model.limits.violation(x[k:k + 1])
            fails.append((k, f"outside the limits at step {k} (s = {float(s[k]):.6g} m; worst violation "
                             f"{float(viol[0]):.3g})"))
        if x.shape[0] > 1:
            ds = float((s[1:] - s[:-1]).max())
            jump = (x[1:] - x[:-1]).abs() / self.bounds(ds)
            if bool((jump > 1).any()):
                k = int((jump > 1).any(-1).nonzero()[0])
                j = int(jump[k].argmax())
                fails.append((k + 1, f"discontinuous between steps {k} and {k + 1}: {self.model.limits.names[j]} "
                                     f"changes by {float((x[k + 1, j] - x[k, j]).abs()):.3g} (bound "
                                     f"{float(self.bounds(ds)[j]):.3g})"))
        clear = None if self.avoid is None else self.avoid.clearance_of_joints(q)
        if clear is not None and bool((clear < self.avoid.clearance).any()):
            k = int((clear < self.avoid.clearance).nonzero()[0])
            fails.append((k, f"clearance {float(clear[k]):.3g} m < {self.avoid.clearance:.3g} m to the obstacles at "
                             f"step {k} (s = {float(s[k]):.6g} m)"))
        if not reason and fails:
            reason = min(fails, key=lambda f: f[0])[1]
        return FTLPlan(q, x, s, tip_err, dev, dev_max, not reason, reason, self.length, clear)


def plan_ftl(model, path, steps: int | None = None, options: FTLOptions = FTLOptions(), scene=None,
             clearance: float = 0.0) -> FTLPlan:
    """Plan the follow-the-leader insertion of ``model`` (any SolverModel with a body, e.g. an arm
    :class:`~dacr_learn.arm.Composite`; a robot file for the bare analytic model) along ``path`` ((W, 3) [m] in
    the model's base frame, or a :class:`~.path.Path`) in ``steps`` steps (default: spacing ≤
    ``options.spacing``·L). scene: obstacles (a :class:`~dacr_learn.scene.Scene`, a scene YAML path or dict, in
    the model's base frame, the arm's for an arm composite): success then also needs every step's body (and an
    arm's links) at least ``clearance`` [m] from them. See the module docstring; the plan's figures are those of
    :mod:`.metric`."""
    model = as_solver_model(model)
    body(model, model.limits.project(torch.zeros(1, model.limits.num_variables, dtype=F64)))   # none: ValueError
    avoid = None if scene is None else Avoidance(model, load_scene(scene), clearance)
    path = path if isinstance(path, Path) else Path(path)
    planner = _Planner(model, path, options, avoid)
    stop = min(path.length, planner.length)
    if steps is None:
        steps = math.ceil(stop / (options.spacing * planner.length)) + 1
    if steps < 2:
        raise ValueError(f"steps: expected >= 2, got {steps}")
    s = torch.linspace(0.0, stop, steps, dtype=F64)
    x0, reason = planner.first()
    if x0 is None:
        n = model.limits.num_variables
        x = model.limits.project(model.rest.to(F64)).expand(steps, n).clone()
        plan = planner.verdict(x, s, reason)
        return plan
    x, late = planner.follow(x0, s)
    return planner.verdict(x, s, reason or late)
