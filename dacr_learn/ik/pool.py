"""The starts of a batched IK solve in a working batch that stays full (docs/ik.md): restarts overlap with the
other starts instead of running as a tail of few rows; the targets may split into shards that run on parallel
threads (:func:`run_sharded`).

:func:`pool_multi_start` iterates the B·K slots' starts with :func:`~.refine.lm_iteration` on whole tensors (no row
gathers or scatters per iteration). A row leaves the batch when it converges (its slot is solved; the slot's other
starts leave too) or stalls (``max_iterations``, or λ past :data:`~.refine.STALL_LAMBDA`). Once :data:`REFILL` of
the batch has left, it drops those rows and takes new ones: the slots' first starts not yet begun, then new uniform
starts of the unsolved slots that have no live start (without ``accept``, of position targets, while the batch is
shorter than :data:`TAIL_ROWS`, also of those whose live starts have all run :data:`RACE_AFTER` iterations: new
starts race the slow ones instead of waiting for them to stall) — one each, more while they fill the batch up to
:data:`TAIL_ROWS` (at most ``max_fan_out`` at once) —, within the same budget of starts per slot as the grouped
restarts of :mod:`.solver`. When few rows are left, solved slots that duplicate another solution of their target are
reopened (twice at most), as in :mod:`.solver`.

With a further condition on a solution (``accept``, e.g. the clearance of a scene, :mod:`.collision`) a row whose
tip has converged leaves the batch undecided; at the next refill the first such row of each slot is checked (one
batched check, :func:`_decide`): an accepted row solves its slot, a rejected one is a candidate like a stalled row, and
``near`` may move the unsolved slots' new starts towards accepted solutions of the same target (not those of slots
reopened as duplicates: near another solution they would find it again). While the batch is *crowded* (fewer than
:data:`CROWDED` of the converged starts checked so far pass, once :data:`SAMPLE` are checked; e.g. a robot on an arm
behind a port, where about 4 in 10 converged seeds fail), every new start of a slot whose target has a solution is
drawn near one (``near``'s share 1), and restarts fill the batch only up to :data:`CROWDED_TAIL_ROWS`: each of their
rows also costs a check, and near a solution one start per slot mostly suffices. A row that has not converged after
:data:`RETIRE_AFTER` iterations then stops (a candidate, like a stalled row) when its target already has a solution
(once per slot, so that slow restarts cannot spend the slot's budget; not for slots reopened as duplicates): its
slot restarts near that solution, which mostly converges clear within a
few iterations, where the slow row's pose-bank seed converges in about as many more and collides about half the
time (the robot on the arm behind the port).
"""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor

from ..checks import F64
from .adapters import SolverModel
from .refine import STALL_LAMBDA, lm_iteration, residual

REFILL = 1 / 16   # refill once this fraction of the batch has left it (or nothing is left)
DUPLICATE_CHECK_BELOW = 0.02   # look for duplicate solutions once fewer live rows than this fraction of slots
CROWDED = 0.75    # with ``accept`` and ``near``: crowded while fewer than this fraction of the converged starts pass,
SAMPLE = 64       # decided once this many are checked (module docstring)
CROWDED_TAIL_ROWS = 512   # restarts fill the batch up to this many rows while crowded (their rows are checked too)
RETIRE_AFTER = 6  # while crowded: a row still unconverged after this many LM iterations, of a target that has a
                  # solution, restarts near one (module docstring)
RACE_AFTER = 8    # position targets without ``accept``, in a short batch: a slot whose live starts all have run this
                  # many iterations takes new starts beside them (the first to converge solves it; pose: no gain)
TAIL_ROWS = 1024  # restarts fill the batch up to this many rows: below it a step costs about the same whatever its rows


def start_budget(restarts: int, fan_out: int, max_fan_out: int) -> int:
    """Starts a slot may take in all: its first and those of ``restarts`` grouped restarts (fan_out, doubling, at
    most max_fan_out each)."""
    return 1 + sum(min(fan_out * 2 ** i, max_fan_out) for i in range(restarts))


class _Batch:
    """The working batch: per row its slot, target, LM state and iterations since its start."""

    def __init__(self, model: SolverModel, position: Tensor, rotation: Tensor | None, damping: float, k: int,
                 iteration: Callable = lm_iteration):
        self.model, self.position, self.rotation, self.damping, self.k = model, position, rotation, damping, k
        self.iteration = iteration
        self.evaluate_in_step = iteration is not lm_iteration     # the compiled iteration: see keep_and_add
        self.slot = torch.zeros(0, dtype=torch.long)
        self.since = torch.zeros(0, dtype=torch.long)
        self.pos_rows = position.new_zeros(0, 3)
        self.rot_rows = None if rotation is None else position.new_zeros(0, 3, 3)
        self.state = None

    def keep_and_add(self, keep: Tensor, slots: Tensor, x0: Tensor) -> None:
        """Keep the rows ``keep`` (indices), add starts x0 (R, D) of ``slots`` (R,)."""
        rows = [None if t is None else t.index_select(0, keep)          # on CPU about 3× faster than t[keep]
                for t in (*(self.state or ()), self.pos_rows, self.rot_rows, self.slot, self.since)]
        if slots.numel():
            target = slots // self.k
            pos = self.position.index_select(0, target)
            rot = None if self.rotation is None else self.rotation.index_select(0, target)
            x = self.model.limits.project(x0.to(F64))
            if self.evaluate_in_step:   # the next (compiled) step evaluates them, not ~250 eager operations here:
                n, res = x.shape[0], 3 if rot is None else 6      # r = 0 and J = 0 make x its own trial, kept at
                cost = x.new_full((n,), float("inf"))             # cost ∞ with λ/3 = damping (not an iteration)
                r, jac, pe, re = x.new_zeros(n, res), x.new_zeros(n, res, x.shape[1]), cost.clone(), cost.clone()
                lam, since = torch.full_like(cost, 3 * self.damping), torch.full_like(slots, -1)
            else:
                r, jac, pe, re = residual(self.model, x, pos, rot)
                cost = (r * r).sum(-1)
                lam, since = torch.full_like(cost, self.damping), torch.zeros_like(slots)
            new = [x, r, jac, cost, lam, pe, re, pos, rot, slots, since]   # the LM state, then per row: target,
                                                                             # slot, iterations
            rows = new if self.state is None else [
                None if old is None else torch.cat([old, n]) for old, n in zip(rows, new, strict=True)]
        self.state, (self.pos_rows, self.rot_rows, self.slot, self.since) = tuple(rows[:7]), rows[7:]

    def step(self) -> None:
        self.state = self.iteration(self.model, self.state, self.pos_rows, self.rot_rows)
        self.since += 1


def pool_multi_start(model: SolverModel, starts: Tensor, position: Tensor, rotation: Tensor | None,
                     gen: torch.Generator, k: int, tolerance: tuple[float, float], damping: float,
                     max_iterations: int, budget: int, max_fan_out: int, pool: int, redundant: bool,
                     keep_first: bool, dedupe, accept: Callable[[Tensor], Tensor] | None = None,
                     near: Callable[..., Tensor] | None = None, iteration: Callable = lm_iteration
                     ) -> tuple[Tensor, Tensor]:
    """Refine the first starts (M, D) of the M = B·K slots (targets position (B, 3) [m], rotation (B, 3, 3) or
    None; slot i belongs to target i // K) in a working batch of at most ``pool`` rows (module docstring).
    ``tolerance``: (position [m], rotation [rad]) a start must reach (a decade below the solver's);
    ``budget``: starts per slot (at most ``max_fan_out`` at once); ``dedupe(x (B, K, D), solved (B, K))`` → (B, K)
    bool marks the solved slots to reopen (``redundant``: more variables than residuals, so solutions are not
    isolated; ``keep_first``: slot 0 of a target, the warm start's, is never reopened). ``accept(x (R, D))`` → (R,)
    bool: whether a start whose tip converged is a solution (module docstring; None: every one is);
    ``near(uniform (R, D), x (M, D), solved (R, K), gen)`` → (R, D): new starts of unsolved slots from uniform
    samples, given the slots' variables x and, per new start, its target's solved slots (−1 where unsolved).
    ``iteration``: the LM iteration of the batch (:func:`~.refine.lm_iteration`, or the compiled one of :mod:`.fused`).
    Returns each slot's variables (M, D) — its converged start, else its start of least residual — and the LM
    iterations spent on the slot (M,)."""
    m, d = starts.shape
    lim = model.limits
    solved = torch.zeros(m, dtype=torch.bool)
    out_x, out_cost = starts.to(F64).clone(), torch.full((m,), float("inf"), dtype=F64)
    taken, iters = torch.zeros(m, dtype=torch.long), torch.zeros(m, dtype=torch.long)
    batch = _Batch(model, position, rotation, damping, k, iteration)
    queued, dedupe_rounds = 0, 0                                   # first starts begun; duplicate checks done
    live = torch.zeros(0, dtype=torch.bool)
    pending: list[tuple[Tensor, Tensor, Tensor]] = []             # (x, cost, slot) of converged rows to decide
    duplicate = torch.zeros(m, dtype=torch.bool)                  # slots reopened as duplicates
    retired = torch.zeros(m, dtype=torch.bool)                    # slots whose slow row stopped (once at most)
    tally, crowded = [0, 0], False                                # converged starts accepted, checked

    def checked(x: Tensor) -> Tensor:
        ok = accept(x)
        tally[0], tally[1] = tally[0] + int(ok.sum()), tally[1] + ok.numel()
        return ok
    while True:
        size = live.numel()
        n_live = int(live.sum())
        if size == 0 or size - n_live >= max(1, REFILL * size):
            while pending:                    # converged rows to decide; all of them once nothing else is left
                out_cost, pending = _decide(pending, checked, solved, out_x, out_cost)
                live = live & ~solved[batch.slot]
                n_live = int(live.sum())
                if n_live:
                    break
            if queued == m and dedupe_rounds < 2 and redundant and n_live <= DUPLICATE_CHECK_BELOW * m:
                dedupe_rounds += 1                    # few rows left: reopen solved slots that duplicate another
                dup = dedupe(out_x.view(-1, k, d), solved.view(-1, k)).flatten()
                if keep_first:
                    dup.view(-1, k)[:, 0] = False
                reopen = dup & (taken < budget)
                solved &= ~reopen             # the duplicate stays the slot's candidate (its cost is tiny)
                duplicate |= reopen
            if near is not None and tally[1] >= SAMPLE:
                crowded = tally[0] < CROWDED * tally[1]
            keep = live.nonzero().squeeze(-1)
            free = pool - keep.numel()
            first = torch.arange(queued, min(m, queued + free))
            queued += first.numel()
            slots, x0 = [first], [starts[first]]
            free -= first.numel()
            if free > 0 and queued == m:
                alive = torch.zeros(m, dtype=torch.bool).index_fill_(0, torch.cat([batch.slot[keep], first]), True)
                if accept is None and rotation is None and keep.numel() < TAIL_ROWS:   # race slow starts
                    young = torch.zeros(m, dtype=torch.bool).index_fill_(0, torch.cat(
                        [batch.slot[keep][batch.since[keep] < RACE_AFTER], first]), True)
                    alive &= young
                needy = (~solved & ~alive & (taken < budget)).nonzero().squeeze(-1)
                if needy.numel():                 # fill up to TAIL_ROWS: a step of fewer rows costs about as much
                    share = max(1, -(-((CROWDED_TAIL_ROWS if crowded else TAIL_ROWS) - keep.numel())
                                       // needy.numel()))
                    each = torch.clamp(budget - taken[needy], max=min(max_fan_out, share))
                    more = needy.repeat_interleave(each)[:free]
                    slots.append(more)
                    fresh = lim.sample(more.numel(), gen)
                    if near is not None:                # not for duplicates: they would find the same again
                        solutions = torch.where(solved, torch.arange(m), -1).view(-1, k)[more // k]
                        fresh = near(fresh, out_x, solutions.masked_fill(duplicate[more].unsqueeze(-1), -1), gen,
                                     1.0 if crowded else None)
                    x0.append(fresh)
            slots = torch.cat(slots)
            taken.index_add_(0, slots, torch.ones_like(slots))
            if slots.numel() == 0 and keep.numel() == 0:
                break
            batch.keep_and_add(keep, slots, torch.cat(x0))
            live = torch.ones(batch.slot.numel(), dtype=torch.bool)
        batch.step()
        iters.index_add_(0, batch.slot, (live & (batch.since > 0)).long())   # not the step that evaluated new rows
        x, _, _, cost, lam, pe, re = batch.state
        conv = live & (pe <= tolerance[0]) & (re <= tolerance[1])
        if conv.any():
            rows = conv.nonzero().squeeze(-1)
            if accept is None:                                    # the first converged row of a slot solves it
                _take_solutions(x[rows], cost[rows], batch.slot[rows], solved, out_x, out_cost)
            else:                                                 # decided at the next refill
                pending.append((x[rows], cost[rows], batch.slot[rows]))
        stall = live & ~conv & ((batch.since >= max_iterations) | (lam >= STALL_LAMBDA))
        if stall.any():                                           # a stalled row: a candidate of least residual
            rows = stall.nonzero().squeeze(-1)
            out_cost = _take_candidates(x[rows], cost[rows], batch.slot[rows], solved, out_x, out_cost)
        if crowded:                                   # slow rows of targets with a solution: restart near one
            slow = (live & ~conv & ~stall & (batch.since >= RETIRE_AFTER) & ~retired[batch.slot]
                    & ~duplicate[batch.slot] & solved.view(-1, k).any(-1)[batch.slot // k])
            if slow.any():
                rows = slow.nonzero().squeeze(-1)
                out_cost = _take_candidates(x[rows], cost[rows], batch.slot[rows], solved, out_x, out_cost)
                retired[batch.slot[rows]] = True
                stall = stall | slow
        live = live & ~conv & ~stall & ~solved[batch.slot]
    return out_x, iters


def _take_solutions(x: Tensor, cost: Tensor, slot: Tensor, solved: Tensor, out_x: Tensor, out_cost: Tensor) -> None:
    """Rows x (R, D) with cost (R,) of slots (R,) that solve them: the first row of each unsolved slot becomes its
    solution (``solved``, ``out_x``, ``out_cost`` updated in place)."""
    m = solved.numel()
    win = torch.full((m,), slot.numel(), dtype=torch.long).scatter_reduce(
        0, slot, torch.arange(slot.numel()), "amin")
    newly = (win < slot.numel()) & ~solved
    out_x[newly], out_cost[newly] = x[win[newly]], cost[win[newly]]
    solved |= newly


def _decide(pending: list[tuple[Tensor, Tensor, Tensor]], accept: Callable[[Tensor], Tensor], solved: Tensor,
            out_x: Tensor, out_cost: Tensor) -> tuple[Tensor, list[tuple[Tensor, Tensor, Tensor]]]:
    """Decide the converged rows ``pending`` [(x (R, D), cost (R,), slot (R,)), …]: the first row of every slot still
    unsolved is checked (``accept``); an accepted row solves its slot (the slot's other rows are dropped), a
    rejected one is a candidate (:func:`_take_candidates`). Updates ``solved``, ``out_x`` in place; returns the
    costs (M,) and the rows left to decide (of slots whose checked row was rejected)."""
    x, cost, slot = (torch.cat(t) for t in zip(*pending, strict=True))
    open_ = ~solved[slot]
    x, cost, slot = x[open_], cost[open_], slot[open_]
    n = slot.numel()
    if n == 0:
        return out_cost, []
    win = torch.full((solved.numel(),), n, dtype=torch.long).scatter_reduce(0, slot, torch.arange(n), "amin")
    first = torch.zeros(n, dtype=torch.bool).index_fill_(0, win[win < n], True)
    xf, cf, sf = x[first], cost[first], slot[first]
    ok = accept(xf)
    _take_solutions(xf[ok], cf[ok], sf[ok], solved, out_x, out_cost)
    out_cost = _take_candidates(xf[~ok], cf[~ok], sf[~ok], solved, out_x, out_cost)
    rest = ~first & ~solved[slot]
    return out_cost, [(x[rest], cost[rest], slot[rest])] if bool(rest.any()) else []


def _take_candidates(x: Tensor, cost: Tensor, slot: Tensor, solved: Tensor, out_x: Tensor, out_cost: Tensor
                     ) -> Tensor:
    """Rows x (R, D) with cost (R,) of slots (R,) that did not solve them: an unsolved slot keeps its row of least
    cost in ``out_x`` (in place); returns the updated costs (M,)."""
    if slot.numel() == 0:
        return out_cost
    best = out_cost.scatter_reduce(0, slot, cost, "amin")
    better = (cost <= best[slot]) & (cost < out_cost[slot]) & ~solved[slot]
    out_x[slot[better]] = x[better]
    return torch.where(solved, out_cost, best)



def shards(b: int, count: int) -> list[slice]:
    """The target ranges of ``count`` shards of about equal size of B targets (fewer when B < count)."""
    size = -(-b // max(1, min(count, b)))
    return [slice(i, min(b, i + size)) for i in range(0, b, size)]


def run_sharded(fn: Callable[[int], object], count: int) -> list:
    """[fn(0), …, fn(count − 1)], on min(count, torch threads) Python threads, each op then on one torch thread (the
    shards' small operations use both cores, which intra-op threads do not); torch's thread count is restored."""
    threads = min(count, torch.get_num_threads())
    if threads < 2:
        return [fn(i) for i in range(count)]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(threads) as workers:
            return list(workers.map(fn, range(count)))
    finally:
        torch.set_num_threads(before)
