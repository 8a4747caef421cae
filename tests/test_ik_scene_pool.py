"""The working batch with a condition on solutions (ik/pool.py with ``accept`` and ``near``): while many converged
starts fail the condition (crowded), restarts start near a solution of their target; otherwise the solve is the
plain one. Checked on the constant-curvature robot with a synthetic condition (each segment's first bending variable
≥ 0, an eighth of the admissible set) against the tip residual recomputed from the returned variables."""
from __future__ import annotations

import torch
from conftest import spec_by_name

import dacr_learn.ik.pool as pool_module
from dacr_learn.ik import ConstantCurvature
from dacr_learn.ik.pool import pool_multi_start, start_budget
from dacr_learn.ik.refine import residual

F64 = torch.float64
SPEC = spec_by_name("tdcr_3seg_equal")
TOL = (1e-7, 1e-6)
BENDS = [0, 3, 6]   # each segment's first bending variable: the synthetic condition wants them all >= 0


def solve(model, starts, pose, k, accept, near, seed=0):
    """pool_multi_start on targets ``pose`` (B, 4, 4) with the solver's settings; (variables (M, D), rows checked)."""
    checked = []

    def counted(x):
        ok = accept(x)
        checked.append(ok)
        return ok

    x, _ = pool_multi_start(model, starts, pose[:, :3, 3], pose[:, :3, :3], torch.Generator().manual_seed(seed), k,
                            TOL, 1e-3, 25, start_budget(8, 4, 64), 64, 8192, True, False,
                            lambda x, ok: torch.zeros_like(ok), counted, near)
    return x, torch.cat(checked) if checked else torch.zeros(0, dtype=torch.bool)


def near_spy(model, calls):
    """A ``near`` like Avoidance.restarts: rows whose target has a solution start within 0.05 scales of one (with
    probability ``share``, default 3/4), projected onto the limits; records each call's share."""
    def near(uniform, x, solved, gen, share=None):
        calls.append(share)
        share = 0.75 if share is None else share
        pick = (solved >= 0) & (torch.rand(uniform.shape[0], generator=gen, dtype=F64) < share).unsqueeze(-1)
        rows = pick.any(-1).nonzero().squeeze(-1)
        out = uniform.clone()
        if rows.numel():
            centre = x[solved[rows].gather(1, pick[rows].to(torch.long).argmax(1, keepdim=True)).squeeze(1)]
            offset = (2 * torch.rand(centre.shape, generator=gen, dtype=F64) - 1) * 0.05
            out[rows] = model.limits.project(centre + offset * model.limits.scale)
        return out
    return near


def targets_and_starts(model, b, k, seed):
    gen = torch.Generator().manual_seed(seed)
    x = model.limits.sample(b, gen)
    x[:, BENDS] = x[:, BENDS].abs()                       # every target has a solution that passes the condition
    pose = torch.eye(4, dtype=F64).repeat(b, 1, 1)
    tip = model.tip_and_jacobian(x)
    pose[:, :3, 3], pose[:, :3, :3] = tip.position, tip.rotation
    return pose, model.limits.sample(b * k, gen)


def converged(model, x, pose, k):
    rows = torch.arange(pose.shape[0]).repeat_interleave(k)
    _, _, pe, re = residual(model, x, pose[rows, :3, 3], pose[rows, :3, :3])
    return (pe <= TOL[0]) & (re <= TOL[1])


def test_crowded_condition_restarts_near_a_solution_and_every_flagged_slot_passes(monkeypatch):
    """An eighth of the admissible set passes: fewer than CROWDED of the converged starts pass, so the restarts of
    slots whose target has a solution are all drawn near one (``near`` asked with share 1); every returned slot
    that converged passes the condition, nearly all do. Never crowded (CROWDED = 0): ``near`` keeps its default
    share."""
    model, b, k = ConstantCurvature(SPEC), 24, 6
    pose, starts = targets_and_starts(model, b, k, seed=2)
    accept = lambda x: (x[:, BENDS] >= 0).all(-1)                # noqa: E731
    calls = []
    x, checked = solve(model, starts, pose, k, accept, near_spy(model, calls))
    ok = converged(model, x, pose, k) & accept(x)
    assert ok.double().mean() >= 0.95 and 1.0 in calls
    assert checked.double().mean() < pool_module.CROWDED and len(checked) >= pool_module.SAMPLE
    monkeypatch.setattr(pool_module, "CROWDED", 0.0)
    never = []
    x_never, _ = solve(model, starts, pose, k, accept, near_spy(model, never))
    assert None in never and 1.0 not in never
    assert (converged(model, x_never, pose, k) & accept(x_never)).double().mean() >= 0.95


def test_uncrowded_condition_gives_the_plain_solutions():
    """Every converged start passes: never crowded (no share-1 restarts) and, as every start converges here (starts
    near the targets' configurations), each slot's solution is the plain solve's bit for bit."""
    model, b, k = ConstantCurvature(SPEC), 16, 6
    gen = torch.Generator().manual_seed(2)
    truth = model.limits.sample(b, gen)
    pose = torch.eye(4, dtype=F64).repeat(b, 1, 1)
    tip = model.tip_and_jacobian(truth)
    pose[:, :3, 3], pose[:, :3, :3] = tip.position, tip.rotation
    offset = (2 * torch.rand(b * k, truth.shape[1], generator=gen, dtype=F64) - 1) * 0.02 * model.limits.scale
    starts = model.limits.project(truth.repeat_interleave(k, 0) + offset)
    calls = []
    x, checked = solve(model, starts, pose, k, lambda x: torch.ones(x.shape[0], dtype=torch.bool),
                       near_spy(model, calls))
    plain, _ = solve(model, starts, pose, k, lambda x: torch.ones(x.shape[0], dtype=torch.bool), None)
    assert converged(model, x, pose, k).all() and checked.all() and 1.0 not in calls
    assert torch.equal(x, plain)


def test_crowded_slow_rows_restart_near_a_solution(monkeypatch):
    """While crowded, a row still unconverged after RETIRE_AFTER iterations of a target that has a solution stops
    (a candidate of its slot) and its slot restarts near one, once per slot: with RETIRE_AFTER = 2 more rows leave
    as candidates than when rows never retire, and nearly every returned slot still
    converged and passes the condition."""
    model, b, k = ConstantCurvature(SPEC), 24, 6
    pose, starts = targets_and_starts(model, b, k, seed=2)
    accept = lambda x: (x[:, BENDS] >= 0).all(-1)                # noqa: E731
    take = pool_module._take_candidates
    left = {}
    for after in (2, 10 ** 9):
        monkeypatch.setattr(pool_module, "RETIRE_AFTER", after)
        rows = []

        def spy(x, *rest, rows=rows):
            rows.append(x.shape[0])
            return take(x, *rest)
        monkeypatch.setattr(pool_module, "_take_candidates", spy)
        x, _ = solve(model, starts, pose, k, accept, near_spy(model, []))
        assert (converged(model, x, pose, k) & accept(x)).double().mean() >= 0.95
        left[after] = sum(rows)
    assert left[10 ** 9] < left[2]
