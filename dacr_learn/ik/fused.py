"""The LM iteration of the working batch (:mod:`.pool`) compiled as one graph by ``torch.compile`` (docs/ik.md).

Eager, one iteration of a pose solve of the 3-segment robot is about 400 tensor operations, each a pass over the
working batch in memory (float64). Inductor's CPU code generation fuses them into a few dozen loops over the rows in
two C++ functions: the same maths (:func:`~.refine.lm_iteration` with the SPD solve written out,
:func:`~.refine.spd_solve_unrolled`, and small products as multiply-sums, :func:`~.refine.fused_matmul`, which
Inductor fuses instead of calling LAPACK and BLAS), equal to the eager iteration up to rounding. Row counts are
dynamic: one compilation serves every batch of :data:`MIN_ROWS` rows or more (smaller batches take the eager
iteration: torch specialises sizes 0 and 1, and a compiled step gains little there). The loops are scalar
(:data:`INDUCTOR_OPTIONS`) and a large batch runs in chunks (:data:`CHUNK_ROWS`): each about halves the time per row
of a large batch. The working batch's new rows enter it unevaluated and the step evaluates them (:mod:`.pool`).

Compiling takes minutes once per robot and task (pose, position) and process, once more for a sharded solve (one
torch thread per shard); torch caches the compiled code on disk (its Inductor cache directory), which shortens, not
removes, the compilation in a later process (its tracing stays). So it is off by default:
``IKOptions(fused=True)`` turns it on for the analytic constant-curvature model (one compiled iteration per robot
spec and task, kept for the process); other models run the eager iteration.
"""
from __future__ import annotations

import threading
import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from .adapters import ConstantCurvature, SolverModel
from .refine import fused_matmul, lm_iteration, spd_solve_unrolled

MIN_ROWS = 64   # batches below this take the eager iteration
CHUNK_ROWS = 2048   # larger batches run in equal chunks of at most this many rows: their intermediates stay in cache
                    # (4,000 rows of a pose solve: ~1.5× the time per row of 2,000, whole)
_COMPILED: dict[tuple, Callable] = {}
_FIRST_CALL = threading.Lock()
INDUCTOR_OPTIONS = {"cpp.simdlen": 1}   # scalar C++ loops: the rows' small inner dimensions (3, 6, 9) fill 4-lane
                                        # AVX2 vectors badly; the scalar step takes half the time at 4,000 rows
STANCE = "default"   # torch.compiler's stance of the compiled calls; "default": guards skipped (fused_iteration)


def fused_iteration(model: SolverModel) -> Callable[[SolverModel, tuple, Tensor, Tensor | None], tuple]:
    """An iteration with :func:`~.refine.lm_iteration`'s signature and results (state, targets → new state) that runs
    the compiled graph (module docstring) for batches of at least :data:`MIN_ROWS` rows of the analytic model;
    :func:`~.refine.lm_iteration` itself for other models. Nothing is compiled before the first call."""
    if not isinstance(model, ConstantCurvature):
        return lm_iteration
    spec = model.spec

    def iteration(model_: SolverModel, state: tuple[Tensor, ...], position: Tensor, rotation: Tensor | None
                  ) -> tuple[Tensor, ...]:
        if state[0].shape[0] < MIN_ROWS:
            return lm_iteration(model_, state, position, rotation)
        key = (spec, rotation is None)
        rot = None if rotation is None else rotation.contiguous()       # fixed strides: no recompilation
        args = tuple(t.contiguous() for t in state), position.contiguous(), rot
        step = _COMPILED.get(key)
        if step is None:
            with _FIRST_CALL, warnings.catch_warnings():     # one compilation when shards call it on parallel threads
                warnings.filterwarnings("ignore", message=".*lru_cache", category=UserWarning)   # a spec's constants
                if key not in _COMPILED:
                    step = _compile(model_)
                    out = step(*args)                                     # compiles
                    _COMPILED[key] = step
                    return out
            step = _COMPILED[key]
        # Dynamo's guards are skipped (skip_guard_eval_unsafe: its one compiled graph runs unchecked): every call of a
        # key's step has the answers of its first — the same count of distinct contiguous float64 tensors (the LM
        # state), sizes but the rows fixed by the spec and task, rows ≥ MIN_ROWS (dynamic: torch only specialises 0
        # and 1), rotation None or not per key, the spec's constants closed over per key; test_ik_fused checks, guards
        # evaluated in STANCE "fail_on_recompile", that calls of other row counts (and chunks) do not recompile.
        n = state[0].shape[0]
        with torch.compiler.set_stance(STANCE, skip_guard_eval_unsafe=STANCE == "default"):
            if n <= CHUNK_ROWS:
                return step(*args)
            size = -(-n // -(-n // CHUNK_ROWS))                             # equal chunks, ≥ CHUNK_ROWS / 2 rows
            parts = [step(tuple(t[i:i + size] for t in args[0]), args[1][i:i + size],
                          None if rot is None else rot[i:i + size]) for i in range(0, n, size)]
        return tuple(torch.cat(p) for p in zip(*parts, strict=True))

    return iteration


def _compile(model: SolverModel) -> Callable:
    def step(state: tuple[Tensor, ...], position: Tensor, rotation: Tensor | None) -> tuple[Tensor, ...]:
        return lm_iteration(model, state, position, rotation, solve=spd_solve_unrolled, matmul=fused_matmul)
    return torch.compile(step, dynamic=True, fullgraph=True, options=INDUCTOR_OPTIONS)
