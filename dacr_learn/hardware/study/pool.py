"""Independent fits of the hardware benchmark on several CPU cores: a process pool, or in line.

Every fit seeds torch itself (:func:`.registry.build_model`) and runs on ``threads`` torch threads, so it
gives the same numbers in a worker as in the main process. Workers are spawned (a forked torch process may
hang on the parent's thread pools); each task is timed where it runs. Tasks and results travel as plain
pickles: torch's multiprocessing pickler passes tensors through a socket each, which a loaded machine refused.
"""
from __future__ import annotations

import multiprocessing
import pickle
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

import torch


def timed(fn: Callable, *args: Any) -> tuple[Any, float]:
    """(fn(*args), wall seconds it took)."""
    start = time.perf_counter()
    return fn(*args), time.perf_counter() - start


def _timed_pickled(blob: bytes) -> bytes:
    """A worker's task: the pickle of timed(fn, *args) from the pickle of (fn, args)."""
    fn, args = pickle.loads(blob)
    return pickle.dumps(timed(fn, *args))


def _unpickled(future: Future) -> Future:
    """A future of the unpickled result of a future of a pickle."""
    out: Future = Future()

    def done(f: Future) -> None:
        try:
            out.set_result(pickle.loads(f.result()))
        except BaseException as err:             # a failed task (or a cancelled one) fails its future
            out.set_exception(err)

    future.add_done_callback(done)
    return out


class _Deferred(Future):
    """A future run in line when its result is first asked for (the order of ``result()`` calls)."""

    def __init__(self, fn: Callable, args: tuple):
        super().__init__()
        self._call = (fn, args)

    def result(self, timeout: float | None = None) -> Any:
        if self._call is not None:
            fn, args = self._call
            self._call = None
            self.set_result(fn(*args))
        return super().result(timeout)


class TaskPool:
    """``submit(fn, *args)`` → a future of ``timed(fn, *args)``; with ``jobs`` > 1 in spawned worker
    processes (started on the first submission), else in this process when the result is asked for.
    Use as a context manager (the workers stop on exit). fn and args must pickle (top-level functions)."""

    def __init__(self, jobs: int = 1, threads: int = 1):
        if jobs < 1 or threads < 1:
            raise ValueError(f"TaskPool: expected jobs >= 1 and threads >= 1, got jobs={jobs}, threads={threads}")
        self.jobs, self.threads = jobs, threads
        self._executor: ProcessPoolExecutor | None = None

    def run_here(self, fn: Callable, *args: Any) -> Future:
        """A future of ``timed(fn, *args)`` run in this process when its result is first asked for."""
        return _Deferred(timed, (fn, *args))

    def submit(self, fn: Callable, *args: Any) -> Future:
        if self.jobs == 1:
            return self.run_here(fn, *args)
        if self._executor is None:
            self._executor = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=torch.set_num_threads, initargs=(self.threads,))
        return _unpickled(self._executor.submit(_timed_pickled, pickle.dumps((fn, args))))

    def __enter__(self) -> TaskPool:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._executor is not None:
            self._executor.shutdown(cancel_futures=exc[0] is not None)
            self._executor = None
