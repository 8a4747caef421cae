"""Side-by-side timing shared by the benchmarks: candidates run interleaved, so a noisy, shared
machine slows them alike and their ratio stays meaningful."""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def time_interleaved(fns: dict[str, Callable[[], object]], rounds: int, calls: int = 1,
                     warmup: int = 2) -> dict[str, np.ndarray]:
    """Per-call wall times [s] of each candidate, shape (rounds · calls,).

    Each candidate first runs ``warmup`` times; then ``rounds`` rounds run ``calls`` calls of every
    candidate in turn, the order reversed every other round (neither goes first all the time).
    """
    if rounds < 1 or calls < 1 or warmup < 0:
        raise ValueError(f"rounds and calls must be ≥ 1 and warmup ≥ 0, got {rounds}, {calls}, {warmup}")
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[int]] = {k: [] for k in fns}
    clock = time.perf_counter_ns
    for r in range(rounds):
        order = list(fns.items()) if r % 2 == 0 else list(fns.items())[::-1]
        for name, fn in order:
            ts = samples[name]
            for _ in range(calls):
                t0 = clock()
                fn()
                ts.append(clock() - t0)
    return {k: np.asarray(v, dtype=np.float64) / 1e9 for k, v in samples.items()}
