"""The fast paths of the batched IK solve. The compiled LM iteration of the working batch (dacr_learn.ik.fused): the
unrolled form it compiles equals the eager iteration; small batches and other models take the eager iteration
unchanged; compiled, the iteration matches the eager one and a solve verifies against the independent NumPy check
(minutes of torch.compile: only with ``DACR_TEST_IK_FUSED=1``, as the compiled path is off by default). The pose-bank
seeds (``IKOptions(bank=N)``): verified solutions in fewer iterations, the bank built once per robot and size."""
from __future__ import annotations

import os

import pytest
import torch
from conftest import TDCR3
from test_ik import assert_flagged_solutions_verify, targets_of

from dacr_learn.ik import ConstantCurvature, IKOptions, solve_ik
from dacr_learn.ik import fused as fused_module
from dacr_learn.ik.adapters import SolverModel
from dacr_learn.ik.fused import MIN_ROWS, fused_iteration
from dacr_learn.ik.pool import pool_multi_start
from dacr_learn.ik.refine import fused_matmul, lm_iteration, residual, spd_solve_unrolled
from dacr_learn.ik.solver import pose_bank

F64 = torch.float64


def lm_state(model: ConstantCurvature, n: int, position_only: bool, seed: int):
    """A working-batch state of n random starts towards n random reachable targets, and the targets."""
    g = torch.Generator().manual_seed(seed)
    pos, rot, _ = model.tip_and_jacobian(model.limits.sample(n, g))
    rot = None if position_only else rot
    x = model.limits.sample(n, g)
    r, jac, pe, re = residual(model, x, pos, rot)
    cost = (r * r).sum(-1)
    return (x, r, jac, cost, torch.full_like(cost, 1e-3), pe, re), pos, rot


def assert_states_close(a, b, rtol: float) -> None:
    for name, u, v in zip(("x", "r", "J", "cost", "λ", "pos_err", "rot_err"), a, b, strict=True):
        torch.testing.assert_close(u, v, rtol=rtol, atol=rtol * float(v.abs().max()), msg=name)


@pytest.mark.parametrize("position_only", [False, True])
def test_unrolled_iteration_equals_the_eager_one(position_only):
    """What the compiled graph traces (the LDLᵀ solve written out, products as multiply-sums) is the eager iteration
    (LAPACK solve, BLAS products) up to float64 rounding, over three iterations from random starts."""
    model = ConstantCurvature(TDCR3)
    state, pos, rot = lm_state(model, 200, position_only, seed=1)
    a = b = state
    for _ in range(3):
        a = lm_iteration(model, a, pos, rot)
        b = lm_iteration(model, b, pos, rot, solve=spd_solve_unrolled, matmul=fused_matmul)
    assert_states_close(b, a, rtol=1e-9)


def test_small_batches_and_other_models_take_the_eager_iteration():
    """Below MIN_ROWS rows the fused iteration is the eager one (bit for bit, nothing compiled); a model other than
    the analytic one gets lm_iteration itself."""
    model = ConstantCurvature(TDCR3)
    state, pos, rot = lm_state(model, MIN_ROWS - 1, False, seed=2)
    for u, v in zip(fused_iteration(model)(model, state, pos, rot), lm_iteration(model, state, pos, rot), strict=True):
        assert torch.equal(u, v)
    assert fused_iteration(SolverModel()) is lm_iteration


@pytest.mark.parametrize("position_only", [False, True])
def test_new_rows_evaluated_by_the_step_follow_the_same_path(position_only):
    """With an iteration other than the eager lm_iteration (the compiled one), the working batch's new rows enter
    unevaluated (r = 0, J = 0, cost ∞) and the next step evaluates them: each start then takes the same LM path as
    when evaluated on entry. One start per slot, no restarts: every slot's variables agree to rounding, its
    iterations exactly (the evaluation is not counted), and the converged ones solve the target."""
    model = ConstantCurvature(TDCR3)
    target = targets_of(TDCR3, 40, seed=9)
    position, rotation = target[:, :3, 3], None if position_only else target[:, :3, :3]
    starts = model.limits.sample(80, torch.Generator().manual_seed(3))
    runs = [pool_multi_start(model, starts, position, rotation, torch.Generator().manual_seed(0), 2, (1e-7, 1e-6),
                             1e-3, 25, 1, 64, 8192, False, False, None, iteration=iteration)
            for iteration in (lm_iteration, lambda *args: lm_iteration(*args))]
    (x, iters), (x_step, iters_step) = runs
    assert torch.equal(iters, iters_step) and iters.min() >= 1
    torch.testing.assert_close(x_step, x, rtol=0, atol=1e-9)
    pos, rot, _ = model.tip_and_jacobian(x_step)
    err = torch.linalg.vector_norm(pos - position.repeat_interleave(2, 0), dim=-1)
    assert (err < 1e-6).float().mean() > 0.5


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("DACR_TEST_IK_FUSED") != "1",
                    reason="DACR_TEST_IK_FUSED=1 compiles the iteration (minutes)")
def test_compiled_iteration_matches_and_solves(monkeypatch):
    """Compiled (position targets: the smaller graph), the iteration matches the eager one on batches of four sizes
    and a fused solve flags only solutions the NumPy check verifies, all of them. Dynamic rows: with dynamo's guards
    evaluated, other row counts (also a batch run in chunks) do not recompile (what makes skipping the guards safe),
    skipped they match too.
    Takes 1–4 min on a 2-core machine (the compilation; less with torch's on-disk cache warm)."""
    model = ConstantCurvature(TDCR3)
    fused = fused_iteration(model)
    for n, stance in ((MIN_ROWS, "default"), (3 * MIN_ROWS + 5, "fail_on_recompile"), (700, "default"),
                      (2 * fused_module.CHUNK_ROWS + 5, "fail_on_recompile")):             # in 3 chunks
        state, pos, _ = lm_state(model, n, True, seed=n)
        monkeypatch.setattr(fused_module, "STANCE", stance)
        assert_states_close(fused(model, state, pos, None), lm_iteration(model, state, pos, None), rtol=1e-9)
    target = targets_of(TDCR3, 16, seed=6)[:, :3, 3]
    result = solve_ik(TDCR3, target, n_solutions=4, position_only=True, options=IKOptions(fused=True))
    assert result.success.all()
    assert_flagged_solutions_verify(TDCR3, result, target)


@pytest.mark.parametrize("position_only", [False, True])
def test_pose_bank_seeds_verify_and_save_iterations(position_only):
    """Seeded by a pose bank, every slot of 24 random reachable targets is solved, every flagged solution passes the
    independent NumPy check, and the LM iterations spent are fewer than from uniform starts (same seed); with q0, slot
    0 still starts there (its solution comes first and is q0's own when q0 solves the target)."""
    target = targets_of(TDCR3, 24, seed=8)
    goal = target[:, :3, 3] if position_only else target
    plain = solve_ik(TDCR3, goal, n_solutions=4, position_only=position_only)
    banked = solve_ik(TDCR3, goal, n_solutions=4, position_only=position_only, options=IKOptions(bank=2048))
    assert banked.success.all()
    assert_flagged_solutions_verify(TDCR3, banked, goal)
    assert banked.iterations.sum() < 0.8 * plain.iterations.sum()
    q0 = plain.q[:, 0]
    warm = solve_ik(TDCR3, goal, n_solutions=4, position_only=position_only, q0=q0, options=IKOptions(bank=2048))
    assert torch.allclose(warm.q[:, 0], q0, atol=1e-6)


def test_pose_bank_is_built_once_and_checked():
    """The analytic model's bank is kept per robot spec and size; a negative size is a clear error."""
    model = ConstantCurvature(TDCR3)
    assert pose_bank(model, 256) is pose_bank(ConstantCurvature(TDCR3), 256)
    assert pose_bank(model, 256) is not pose_bank(model, 512)
    with pytest.raises(ValueError, match="bank"):
        IKOptions(bank=-1)
