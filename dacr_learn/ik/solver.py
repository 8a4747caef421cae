"""Batched inverse kinematics: several solutions per target, exact to micrometres, inside every limit.

:func:`solve_ik` returns, for each of B targets, K joint vectors. Each slot starts from a seed (a warm start,
a learned sampler's sample, or a uniform sample of the admissible set) and is refined by
:func:`~.refine.levenberg_marquardt`; slots that fail are restarted from new seeds, and successful slots that
duplicate another solution of the same target are restarted too, to find distinct ones (a redundant robot has
a continuum of solutions). The verdict ``success`` comes from the model's own check of the returned joints
(tip from the joints alone, limits, displacement constraint), not from the solver's internal state.

The refinement is :mod:`.refine` (Levenberg–Marquardt with the limits inside the step, docs/ik.md); starts that
stall restart in groups (:data:`FAN_OUT`), so the tail of hard targets costs few passes over the batch.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from ..checks import F64
from ..metrics import rotation_geodesic
from ..scene import load_scene
from .adapters import ConstantCurvature, SolverModel, as_solver_model
from .collision import Avoidance
from .fused import fused_iteration
from .pool import pool_multi_start, run_sharded, shards, start_budget
from .refine import STALL_LAMBDA, Refinement, lm_iteration
from .seeds import PoseBank
from .targets import check_q0, check_targets
from .workers import run_in_processes


@dataclass(frozen=True)
class IKOptions:
    """Settings of :func:`solve_ik`.

    pos_tolerance [m], rot_tolerance [rad]: the position and rotation errors a solution must reach (the names of
    pytorch-kinematics' IK; the CLI's ``--tolerance POS ROT``); max_iterations: LM iterations of one
    start; restarts: new starts a slot may take when its start stalls or duplicates another solution;
    distinct: two solutions of a target are distinct when some joint differs by at least this much
    [joint units: m, rad; mm for a servo model]; damping: initial λ (scaled units); seed: of the random
    starts (reproducible results for the same seed and shards); pool: rows of the working batch that stays full
    (:mod:`.pool`; with a scene, converged starts are checked for clearance in batches there), 0 for grouped
    restarts of shrinking batches (:func:`_multi_start`); shards: the pool's targets split into this many parts, run
    on parallel threads (at most torch's thread count at once; the solutions depend on the shards, not on the
    threads); processes: the shards in worker processes instead (:mod:`.workers`; the same solutions; the analytic
    model without a scene only, else ValueError); fused: the pool's LM iteration compiled by torch.compile
    (:mod:`.fused`; the analytic model only; minutes of compilation once per robot and task in a process, cached on
    disk by torch); bank: samples of a pose bank (:class:`~.seeds.PoseBank`) whose tips nearest each target seed the
    slots not started by q0 or ``seeds`` (0: uniform starts; built on first use, kept per robot spec and size for the
    analytic model).
    """

    pos_tolerance: float = 1e-6
    rot_tolerance: float = 1e-5
    max_iterations: int = 25
    restarts: int = 8
    distinct: float = 5e-4
    damping: float = 1e-3
    seed: int = 0
    pool: int = 8192
    shards: int = 1
    processes: bool = False
    fused: bool = False
    bank: int = 0

    def __post_init__(self):
        for name, t, unit in (("pos_tolerance", self.pos_tolerance, "m"), ("rot_tolerance", self.rot_tolerance, "rad")):
            if not (t > 0 and math.isfinite(t)):
                raise ValueError(f"{name}: expected a finite value > 0 [{unit}], got {t}")
        if self.max_iterations < 1 or self.restarts < 0:
            raise ValueError(f"max_iterations >= 1 and restarts >= 0 expected, got {self.max_iterations}, "
                             f"{self.restarts}")
        if self.bank < 0:
            raise ValueError(f"bank: expected >= 0 samples (0: uniform starts), got {self.bank}")
        if self.pool < 0 or self.shards < 1:
            raise ValueError(f"pool >= 0 (0: grouped restarts) and shards >= 1 expected, got {self.pool}, "
                             f"{self.shards}")
        if self.processes and self.pool == 0:
            raise ValueError("processes: worker processes run the working batch's shards; expected pool > 0, got 0")
        if not self.distinct >= 0 or not self.damping > 0:
            raise ValueError(f"distinct >= 0 and damping > 0 expected, got {self.distinct}, {self.damping}")


@dataclass
class IKResult:
    """K solutions of each of B targets, float64, ordered per target (docs/ik.md): successful first; among them
    the one nearest the warm start q0 first when q0 was given, else the one nearest the model's rest
    configuration (least bending); distinct solutions before duplicates.

    q (B, K, N) joint vectors; success (B, K) the model's own verdict (tolerance, limits, constraint);
    pos_err (B, K) [m]; rot_err (B, K) [rad] (0 with position_only); iterations (B, K) LM iterations spent
    on the returned solution's slot over all rounds; distinct (B, K) True for the solutions kept as distinct;
    clearance (B, K) [m] with a scene (else None): the signed clearance of the body (and an arm's links) to the
    obstacles, a lower bound computed from the returned joints alone (:mod:`.collision`; negative = penetration).
    """

    q: Tensor
    success: Tensor
    pos_err: Tensor
    rot_err: Tensor
    iterations: Tensor
    distinct: Tensor = field(default=None)
    clearance: Tensor | None = None

    @classmethod
    def concat(cls, parts: list[IKResult]) -> IKResult:
        """The results of consecutive target batches as one (along B)."""
        return cls(**{f.name: None if getattr(parts[0], f.name) is None else
                      torch.cat([getattr(r, f.name) for r in parts]) for f in fields(cls)})

    def numpy(self) -> dict:
        return {f.name: getattr(self, f.name).cpu().numpy() for f in fields(self) if getattr(self, f.name) is not None}


def _distinct_mask(q: Tensor, ok: Tensor, order: Tensor, threshold: float) -> Tensor:
    """(B, K) True for successful slots that differ from every earlier kept one (in ``order``) by ≥ threshold
    in some joint (greedy, in that order)."""
    b, k, _ = q.shape
    qs = torch.gather(q, 1, order.unsqueeze(-1).expand_as(q))
    oks = torch.gather(ok, 1, order)
    kept = torch.zeros(b, k, dtype=torch.bool)
    for j in range(k):
        diff = (qs[:, :j] - qs[:, j:j + 1]).abs().amax(-1)                              # (B, j)
        dup = ((diff < threshold) & kept[:, :j]).any(-1)
        kept[:, j] = oks[:, j] & ~dup
    out = torch.zeros_like(kept)
    return out.scatter(1, order, kept)


def _order(q: Tensor, x: Tensor, ok: Tensor, cost: Tensor, rest: Tensor, scale: Tensor,
           q0: Tensor | None) -> Tensor:
    """(B, K) slot order: successful first, then by distance to q0 (joint space) or to the rest
    configuration (scaled variables), failed slots by their residual."""
    if q0 is not None:
        key = (q - q0.unsqueeze(1)).abs().amax(-1)
    else:
        key = torch.linalg.vector_norm((x - rest) / scale, dim=-1)
    key = torch.where(ok, key, 1e6 + cost)
    return torch.argsort(key, dim=1, stable=True)


def solve_ik(model_or_spec, target: Tensor, n_solutions: int = 8, q0: Tensor | None = None,
             position_only: bool = False, options: IKOptions = IKOptions(), seeds: Tensor | None = None,
             scene=None, clearance: float = 0.0) -> IKResult:
    """Up to ``n_solutions`` joint vectors per target (see :class:`IKResult` for the fields and their order).

    model_or_spec: a RobotSpec / robot YAML path / dict (analytic CC model), a trained FK model, or an
    :class:`~.adapters.SolverModel`. target: (B, 4, 4) tip poses [m] in the robot's base frame, or (B, 3)
    positions with ``position_only``. q0 (B, N) or (N,): a warm start (the previous command of a
    trajectory): slot 0 starts there and the solution nearest q0 comes first. seeds (B, S, D): further starts
    in the model's variables (e.g. from a learned sampler; used before random ones).
    An unreachable target gets success False and the admissible configuration with the smallest residual.
    scene: obstacles (a :class:`~dacr_learn.scene.Scene`, a scene YAML path or dict; the model's base frame, the
    arm's for an arm composite): success then also needs the body (and an arm's links) at least ``clearance``
    [m] from every obstacle (:mod:`.collision`; the model needs a body), and the result carries ``clearance``.
    """
    model = as_solver_model(model_or_spec)
    avoid = None if scene is None else Avoidance(model, load_scene(scene), clearance)
    if n_solutions < 1:
        raise ValueError(f"n_solutions: expected >= 1, got {n_solutions}")
    if not position_only and not model.has_rotation:
        raise ValueError("position_only: this model gives a tip position only; call with position_only=True")
    target = check_targets(target, position_only)
    b, k, lim = target.shape[0], n_solutions, model.limits
    d = lim.num_variables
    position = target[:, :3, 3] if target.dim() == 3 else target
    rotation = None if position_only else target[:, :3, :3]
    gen = torch.Generator().manual_seed(options.seed)
    starts = lim.sample(b * k, gen).view(b, k, d)
    s = 0
    if seeds is not None:
        if seeds.dim() != 3 or seeds.shape[0] != b or seeds.shape[2] != d or not torch.isfinite(seeds).all():
            raise ValueError(f"seeds: expected finite (B={b}, S, D={d}) variables, got {tuple(seeds.shape)}")
        s = min(k, seeds.shape[1])
        starts[:, :s] = seeds[:, :s].to(F64)
    s = max(s, int(q0 is not None))                              # slot 0 is q0's
    if q0 is not None:
        q0 = check_q0(q0, b, model.num_joints)
        starts[:, 0] = model.variables(q0)
    if options.pool == 0:
        if options.bank and s < k:
            starts[:, s:] = pose_bank(model, options.bank).seeds(target, k - s)
        rows = torch.arange(b).repeat_interleave(k)
        state = Refinement(model, starts.view(-1, d), position[rows], None if rotation is None else rotation[rows],
                           (options.pos_tolerance, options.rot_tolerance), options.damping, avoid)
        x, iters = _multi_start(state, gen, b, k, options, keep_first=q0 is not None)
        return _verified_result(model, x.view(b, k, d), iters.view(b, k), position, rotation, q0, options, avoid)
    parts = shards(b, options.shards)
    gens = [gen] if len(parts) == 1 else [torch.Generator().manual_seed(int(g)) for g in torch.randint(
        2 ** 62, (len(parts),), generator=gen)]
    items = [(starts[t], target[t], None if q0 is None else q0[t], s, gens[i].get_state(), options, position_only)
             for i, t in enumerate(parts)]
    if options.processes:
        if type(model) is not ConstantCurvature or avoid is not None:
            raise ValueError(f"processes: worker processes solve for the analytic constant-curvature model without a "
                             f"scene; got {type(model).__name__}{'' if avoid is None else ' with a scene'} "
                             f"(use processes=False)")
        return IKResult.concat(run_in_processes(_process_shard, [(model.spec, *item) for item in items], len(parts)))
    return IKResult.concat(run_sharded(lambda i: _solve_shard(model, *items[i], avoid), len(parts)))


def _solve_shard(model: SolverModel, starts: Tensor, target: Tensor, q0: Tensor | None, s: int, gen_state: Tensor,
                 options: IKOptions, position_only: bool, avoid: Avoidance | None) -> IKResult:
    """The verified result of one shard of targets (B, 4, 4) or (B, 3) by :func:`~.pool.pool_multi_start` from starts
    (B, K, D), slots s… seeded by the pose bank (``options.bank``), the random starts from a generator of state
    ``gen_state`` (so that threads and worker processes draw the same)."""
    b, k, d = starts.shape
    iteration = fused_iteration(model) if options.fused else lm_iteration
    if options.bank and s < k:
        starts = starts.clone()
        starts[:, s:] = pose_bank(model, options.bank).seeds(target, k - s)
    position = target[:, :3, 3] if target.dim() == 3 else target
    rotation = None if position_only else target[:, :3, :3]
    gen = torch.Generator()
    gen.set_state(gen_state)
    x, iters = pool_multi_start(
        model, starts.reshape(-1, d), position, rotation, gen, k,
        (0.1 * options.pos_tolerance, 0.1 * options.rot_tolerance), options.damping,   # a decade below, as Refinement
        options.max_iterations, start_budget(options.restarts, FAN_OUT, MAX_FAN_OUT), MAX_FAN_OUT, options.pool,
        d >= (3 if rotation is None else 6), q0 is not None, lambda x, ok: _duplicates(model, x, ok, options.distinct),
        None if avoid is None else avoid.accept, None if avoid is None else avoid.restarts, iteration)
    return _verified_result(model, x.view(b, k, d), iters.view(b, k), position, rotation, q0, options, avoid)


_MODELS: dict = {}


def _process_shard(item: tuple) -> IKResult:
    """:func:`_solve_shard` in a worker process (:mod:`.workers`) for the analytic model of a spec (kept per spec, with
    its compiled iteration and pose bank)."""
    spec, starts, target, q0, s, gen_state, options, position_only = item
    if spec not in _MODELS:
        _MODELS[spec] = ConstantCurvature(spec)
    model = _MODELS[spec]
    return _solve_shard(model, starts, target, q0, s, gen_state, options, position_only, None)


_BANKS: dict[tuple, PoseBank] = {}


def pose_bank(model: SolverModel, size: int) -> PoseBank:
    """A pose bank of ``size`` samples of ``model`` (``IKOptions.bank``): for the analytic model built once per robot
    spec and size in a process (a fraction of a second for 8,192 samples of the 3-segment robot), else per call."""
    if not isinstance(model, ConstantCurvature):
        return PoseBank(model, size)
    key = (model.spec, size)
    if key not in _BANKS:
        _BANKS[key] = PoseBank(model, size)
    return _BANKS[key]


FAN_OUT = 4   # new starts a slot takes at once when its starts have stalled, doubled at each further restart
MAX_FAN_OUT = 64
DUPLICATE_CHECK_BELOW = 0.02   # look for duplicate solutions once fewer live starts than this fraction of slots


def _multi_start(state: Refinement, gen: torch.Generator, b: int, k: int, opts: IKOptions,
                 keep_first: bool) -> tuple[Tensor, Tensor]:
    """Run the LM iterations of the B·K slots (one start each, rows 0 … M − 1 of ``state``) together, adding
    starts where needed. A start stalls when it has not converged after ``max_iterations`` iterations or its λ
    passed :data:`STALL_LAMBDA`; a slot whose starts have all stalled takes :data:`FAN_OUT` new uniform starts at
    once, twice as many at each further restart (at most ``restarts`` times, :data:`MAX_FAN_OUT` at once: at
    the end of a batch few rows iterate, so more starts cost little more than one), and a slot is solved by
    the first of its starts that converges (the others stop). When most slots are settled, successful slots that
    duplicate another solution of their target take new starts the same way (twice at most).
    Returns each slot's variables (M, D) — its converged start, or
    the start of least residual — and the iterations spent on the slot (M,)."""
    lim, m, model = state.lim, b * k, state.model
    slot = torch.arange(m)                                            # the slot of each row (start)
    since = torch.zeros(m, dtype=torch.long)                          # iterations of each row
    live = torch.ones(m, dtype=torch.bool)                            # rows still iterating
    used = torch.zeros(m, dtype=torch.long)                           # restarts taken, per slot
    solution = torch.full((m,), -1, dtype=torch.long)                 # the row that solved each slot
    duplicates_checked = 0
    redundant = state.x.shape[1] >= state.tip_rows      # fewer variables than residuals: isolated solutions
    while True:
        conv = state.converged() & live
        first_conv = torch.full((m,), state.x.shape[0], dtype=torch.long).scatter_reduce(
            0, slot[conv], conv.nonzero().squeeze(-1), "amin")
        newly = (solution < 0) & (first_conv < state.x.shape[0])
        solution[newly] = first_conv[newly]
        live &= ~conv & (solution[slot] < 0)                          # a solved slot's other starts stop
        live &= ~((since >= opts.max_iterations) | (state.lam >= STALL_LAMBDA))
        alive = torch.zeros(m, dtype=torch.bool).index_fill_(0, slot[live], True)
        again = (solution < 0) & ~alive & (used < opts.restarts)
        if (duplicates_checked < 2 and redundant and live.sum() <= DUPLICATE_CHECK_BELOW * m
                and not again.any()):
            duplicates_checked += 1                         # most slots settled: look for duplicate solutions
            ok = (solution >= 0).view(b, k)
            x_slot = state.x[solution.clamp_min(0)]
            dup = _duplicates(model, x_slot.view(b, k, -1), ok, opts.distinct)
            if keep_first:
                dup[:, 0] = False
            again = dup.flatten() & (used < opts.restarts)
            solution[again] = -1           # reopened; the duplicate row stays a candidate (it has converged)
            live[torch.isin(slot, again.nonzero().squeeze(-1))] = False
        if again.any():
            reopened = again.nonzero().squeeze(-1)
            slots = reopened.repeat_interleave(torch.clamp(FAN_OUT * 2 ** used[reopened], max=MAX_FAN_OUT))
            fresh = lim.sample(slots.numel(), gen)
            if state.extra is not None:           # a scene: most new starts near a solution of the same target
                fresh = state.extra.restarts(fresh, state.x, solution.view(b, k)[slots // k], gen)
            state.append(fresh, state.position[slots],
                         None if state.rotation is None else state.rotation[slots])
            slot = torch.cat([slot, slots])
            since = torch.cat([since, torch.zeros_like(slots)])
            live = torch.cat([live, torch.ones_like(slots, dtype=torch.bool)])
            used[again] += 1
        rows = live.nonzero().squeeze(-1)
        if rows.numel() == 0:
            break
        state.step(rows)
        since[rows] += 1
    return _slot_results(state, slot, solution, since, m)


def _duplicates(model: SolverModel, x: Tensor, ok: Tensor, threshold: float) -> Tensor:
    """(B, K) True for the successful slots (ok) whose joints, at variables x (B, K, D), duplicate an earlier
    successful slot's (slot order) by :func:`_distinct_mask`."""
    b, k, d = x.shape
    order = torch.argsort((~ok).to(torch.int8), dim=1, stable=True)
    return ok & ~_distinct_mask(model.joints(x.reshape(-1, d)).view(b, k, -1), ok, order, threshold)


def _slot_results(state: Refinement, slot: Tensor, solution: Tensor, since: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """Per slot: the variables of its solving row, else of its row of least cost; and the iterations of all its rows."""
    cost = state.cost.clone()
    best = torch.full((m,), float("inf"), dtype=F64).scatter_reduce(0, slot, cost, "amin")
    is_best = cost <= best[slot]
    pick = torch.full((m,), cost.shape[0], dtype=torch.long).scatter_reduce(
        0, slot[is_best], is_best.nonzero().squeeze(-1), "amin")
    pick = torch.where(solution >= 0, solution, pick)
    iters = torch.zeros(m, dtype=torch.long).index_add_(0, slot, since)
    return state.x[pick], iters


def _verified_result(model: SolverModel, x: Tensor, iters: Tensor, position: Tensor, rotation: Tensor | None,
                     q0: Tensor | None, options: IKOptions, avoid: Avoidance | None = None) -> IKResult:
    """The result of variables x (B, K, D): joints, the model's independent check (and the clearance check of
    ``avoid``), order and distinct flags."""
    b, k, d = x.shape
    q = model.joints(x.view(-1, d))
    check = model.check(q)
    q = q.view(b, k, -1)
    rows = torch.arange(b).repeat_interleave(k)
    pos_err = torch.linalg.vector_norm(check.position - position[rows], dim=-1).view(b, k)
    rot_err = (torch.zeros_like(pos_err) if rotation is None
               else rotation_geodesic(check.rotation, rotation[rows]).view(b, k))
    constraint_ok = (check.constraint <= 1e-9 * max(model.length, 1.0)).view(b, k)
    ok = ((pos_err <= options.pos_tolerance) & (rot_err <= options.rot_tolerance) & check.inside.view(b, k)
          & constraint_ok)
    clearance = None
    if avoid is not None:
        clearance = avoid.verdict(x.view(-1, d)).view(b, k)            # of q = joints(x)
        ok &= clearance >= avoid.clearance
    rest = model.limits.project(model.rest.to(F64))
    order = _order(q, x, ok, pos_err / model.length + rot_err, rest, model.limits.scale, q0)
    distinct = _distinct_mask(q, ok, order, options.distinct)
    pick = lambda t: torch.gather(t, 1, order.view(b, k, *([1] * (t.dim() - 2))).expand_as(t))  # noqa: E731
    return IKResult(q=pick(q), success=pick(ok), pos_err=pick(pos_err), rot_err=pick(rot_err),
                    iterations=pick(iters), distinct=pick(distinct),
                    clearance=None if clearance is None else pick(clearance))
