"""benchmarks/timing.py: the interleaved side-by-side timing the benchmarks share (a fake clock: no timing here)."""
from __future__ import annotations

import importlib.util

import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("benchmark_timing", ROOT / "benchmarks" / "timing.py")
timing = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(timing)


class FakeClock:
    """perf_counter_ns that a candidate advances by its own cost [ns] per call."""

    def __init__(self):
        self.now = 0

    def __call__(self) -> int:
        return self.now

    def candidate(self, cost_ns: int, calls: list):
        def fn():
            self.now += cost_ns
            calls.append(cost_ns)
        return fn


def test_rounds_interleave_and_a_slow_candidate_runs_about_round_seconds_per_round(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr(timing.time, "perf_counter_ns", clock)
    order: list = []
    fns = {"fast": clock.candidate(1_000, order), "slow": clock.candidate(2_000_000, order)}   # 1 µs, 2 ms
    out = timing.time_interleaved(fns, rounds=4, calls=500, warmup=3, round_seconds=0.2)
    assert out["fast"].size == 4 * 500                                   # 0.5 ms per round: all its calls
    assert out["slow"].size == 4 * 100                                   # 0.2 s / 2 ms per round
    assert set(out["fast"]) == {1e-6} and set(out["slow"]) == {2e-3}     # per-call times [s]
    timed = order[2 * 3:]                                                # after the warm-ups
    assert timed[:500] == [1_000] * 500 and timed[500:600] == [2_000_000] * 100      # round 0: fast, slow
    assert timed[600:700] == [2_000_000] * 100                                       # round 1 reversed
    floor = timing.time_interleaved({"slower": clock.candidate(10**9, [])}, 1, 500, warmup=1, round_seconds=0.2)
    assert floor["slower"].size == 20                                    # at least 20 calls per round
    plain = timing.time_interleaved(fns, rounds=2, calls=7, warmup=1)
    assert plain["slow"].size == plain["fast"].size == 14                # without round_seconds: calls each


def test_bad_counts_are_refused():
    with pytest.raises(ValueError, match="rounds and calls must be"):
        timing.time_interleaved({"f": lambda: None}, rounds=0)
