"""Shards of the batched IK solve in worker processes (``IKOptions(processes=True)``, dacr_learn.ik.workers): the same
solutions as on threads (same per-shard generators), reproducible, verified by the independent NumPy check; the
workers are kept between calls, a worker's failure is the caller's error, an interrupt stops them without waiting for
their work, and they stop at exit. The workers run the eager iteration here (the compiled one takes minutes)."""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import ROOT, TDCR3
from test_ik import assert_flagged_solutions_verify, targets_of

from dacr_learn.ik import IKOptions, solve_ik, workers


@pytest.mark.parametrize("position_only", [False, True])
def test_processes_give_the_threads_solutions(position_only):
    """2 shards in worker processes = 2 shards on threads, bit for bit (q, flags, iterations), also seeded by a pose
    bank; twice the same on the kept workers; every slot solved and every flagged solution verifies."""
    target = targets_of(TDCR3, 10, seed=4)
    goal = target[:, :3, 3] if position_only else target
    for bank in (0, 512):
        runs = [solve_ik(TDCR3, goal, n_solutions=4, position_only=position_only,
                         options=IKOptions(seed=5, shards=2, bank=bank, processes=processes))
                for processes in (False, True, True)]
        for other in runs[1:]:
            for name in ("q", "success", "iterations", "distinct"):
                assert torch.equal(getattr(runs[0], name), getattr(other, name)), name
        assert runs[1].success.all()
        assert_flagged_solutions_verify(TDCR3, runs[1], goal)
    pids = [p.pid for p, _ in workers.worker_pool(2).workers]
    solve_ik(TDCR3, goal[:3], n_solutions=2, position_only=position_only, options=IKOptions(shards=2, processes=True))
    assert [p.pid for p, _ in workers.worker_pool(2).workers] == pids           # kept, not restarted


def test_processes_need_the_analytic_model_and_the_pool():
    with pytest.raises(ValueError, match="pool > 0"):
        IKOptions(processes=True, pool=0)
    scene = ROOT / "configs" / "scenes" / "spheres_tdcr3.yaml"
    with pytest.raises(ValueError, match="processes.*scene"):
        solve_ik(TDCR3, targets_of(TDCR3, 2, seed=1), n_solutions=2, scene=scene,
                 options=IKOptions(shards=2, processes=True))


def test_an_interrupt_stops_the_workers_and_a_failure_raises():
    """A KeyboardInterrupt while the workers are busy returns within seconds, the workers stopped and reaped; new
    workers serve the next call (3 items on 2 workers); a worker's exception comes back as a RuntimeError with its
    traceback, and the workers then exit on the stop message (exit code 0), as at exit."""
    busy = workers.worker_pool(2).workers
    interrupt = "import os, signal, time; os.kill(os.getppid(), signal.SIGINT); time.sleep(60)"   # Ctrl-C, mid-work
    t0 = time.perf_counter()
    # Ctrl-C as in a terminal: a background job of a non-interactive shell starts with SIGINT ignored
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            workers.run_in_processes(exec, [interrupt, "import time; time.sleep(60)"], 2)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert time.perf_counter() - t0 < 15
    assert all(not p.is_alive() and p.exitcode is not None for p, _ in busy)
    assert workers.run_in_processes(math.sqrt, [4.0, 9.0, 16.0], 2) == [2.0, 3.0, 4.0]
    idle = workers.worker_pool(2).workers
    with pytest.raises(RuntimeError, match="math domain error"):
        workers.run_in_processes(math.sqrt, [4.0, -1.0], 2)
    assert [p.exitcode for p, _ in idle] == [0, 0]


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("DACR_TEST_IK_FUSED") != "1",
                    reason="DACR_TEST_IK_FUSED=1 compiles the iteration (minutes, in each worker process)")
def test_fused_processes_give_the_threads_solutions():
    """With the compiled iteration (position targets: the smaller graph), 2 shards in worker processes give the
    solutions of 2 shards on threads (each thread on one torch thread, as each worker), all verified. Takes 3–8 min on
    a 2-core machine (the compilation, in this process and in each worker)."""
    target = targets_of(TDCR3, 32, seed=9)[:, :3, 3]          # 64 rows per shard: compiled (>= MIN_ROWS)
    before = torch.get_num_threads()
    torch.set_num_threads(2)                                 # the threaded shards run on one torch thread each
    try:
        runs = [solve_ik(TDCR3, target, n_solutions=4, position_only=True,
                         options=IKOptions(seed=2, shards=2, fused=True, processes=processes))
                for processes in (False, True)]
    finally:
        torch.set_num_threads(before)
    for name in ("q", "success", "iterations"):
        assert torch.equal(getattr(runs[0], name), getattr(runs[1], name)), name
    assert runs[1].success.all()
    assert_flagged_solutions_verify(TDCR3, runs[1], target)


def test_a_workers_progress_bar_leaves_no_semaphore_at_exit():
    """torch's compiler opens tqdm progress bars in the workers; their lock is a thread lock there, so a worker's fast
    exit leaks no semaphore (else the resource tracker warns at the caller's exit)."""
    code = ("from dacr_learn.ik import workers\n"
            "workers.run_in_processes(exec, ['from tqdm import tqdm; list(tqdm(range(2), disable=True))'], 1)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0 and "leaked semaphore" not in out.stderr, out.stderr
