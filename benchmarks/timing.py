"""Side-by-side timing shared by the benchmarks: candidates run interleaved, so a noisy, shared
machine slows them alike and their ratio stays meaningful."""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def time_interleaved(fns: dict[str, Callable[[], object]], rounds: int, calls: int = 1,
                     warmup: int = 2, round_seconds: float | None = None) -> dict[str, np.ndarray]:
    """Per-call wall times [s] of each candidate, shape (rounds · calls_k,).

    Each candidate first runs ``warmup`` times; then ``rounds`` rounds run ``calls`` calls of every
    candidate in turn, the order reversed every other round (neither goes first all the time). With
    ``round_seconds``, a candidate whose median warm-up call takes longer than round_seconds / calls runs
    fewer calls per round, about round_seconds' worth (at least 20): slow candidates keep enough samples
    for their median and p99 without setting the run's length.
    """
    if rounds < 1 or calls < 1 or warmup < 0:
        raise ValueError(f"rounds and calls must be ≥ 1 and warmup ≥ 0, got {rounds}, {calls}, {warmup}")
    clock = time.perf_counter_ns
    per_round = {}
    for name, fn in fns.items():
        warm = []
        for _ in range(warmup):
            t0 = clock()
            fn()
            warm.append(clock() - t0)
        per_round[name] = calls
        if round_seconds is not None and warm:
            per_round[name] = min(calls, max(20, int(round_seconds * 1e9 / max(float(np.median(warm)), 1.0))))
    samples: dict[str, list[int]] = {k: [] for k in fns}
    for r in range(rounds):
        order = list(fns.items()) if r % 2 == 0 else list(fns.items())[::-1]
        for name, fn in order:
            ts = samples[name]
            for _ in range(per_round[name]):
                t0 = clock()
                fn()
                ts.append(clock() - t0)
    return {k: np.asarray(v, dtype=np.float64) / 1e9 for k, v in samples.items()}
