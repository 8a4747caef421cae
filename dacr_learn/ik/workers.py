"""Persistent worker processes for the shards of a batched IK solve (``IKOptions(processes=True)``, docs/ik.md).

The compiled LM iteration (:mod:`.fused`) and the working batch's glue (:mod:`.pool`) hold the GIL, so shards on
Python threads (:func:`~.pool.run_sharded`) share one core. Here each shard runs in a worker process of its own, with
one torch thread: :func:`run_in_processes` ``(fn, items)`` sends item i to worker i mod n and returns
``[fn(item) for item in items]`` in order. The workers start on first use (the ``spawn`` start method: a fresh
interpreter, no fork of a process whose torch and OpenMP are initialised), are kept for the process — like the
compiled iteration, each worker compiles and builds what it needs once — and stop at exit. ``fn`` must be a
module-level function; items and results travel pickled, CPU tensors as NumPy arrays (:func:`dumps`: a fifth of the
time of torch's own pickling, which writes each tensor as a zip archive; no shared memory), so small tensors cost
little: a 1,000 × 8 pose solve sends about 0.6 MB.

A worker ignores Ctrl-C (SIGINT): the caller gets the KeyboardInterrupt, and any failure while waiting for the
workers (an interrupt, a worker that died) stops them all (the next call starts new ones), so a late answer can never
be taken for a later call's. At exit the workers get a stop message, then SIGTERM and SIGKILL after
:data:`STOP_WAIT` seconds each; they are daemonic (multiprocessing ends them too if this process exits otherwise) and
a worker whose parent disappears exits when its pipe closes.
"""
from __future__ import annotations

import atexit
import io
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection

import torch

_NUMPY_DTYPES = {torch.float64, torch.float32, torch.float16, torch.int64, torch.int32, torch.int16, torch.int8,
                 torch.uint8, torch.bool, torch.complex64, torch.complex128}


class _Pickler(pickle.Pickler):
    """Pickles plain CPU tensors as NumPy arrays (unpickled by ``torch.from_numpy``: the same dtype, shape, values)."""

    def reducer_override(self, obj):
        if (type(obj) is torch.Tensor and obj.device.type == "cpu" and obj.layout == torch.strided
                and not obj.requires_grad and obj.dtype in _NUMPY_DTYPES):
            return torch.from_numpy, (obj.numpy(),)
        return NotImplemented


def dumps(obj: object) -> bytes:
    """``obj`` pickled for a worker pipe (:class:`_Pickler`; read back by ``pickle.loads``)."""
    buffer = io.BytesIO()
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buffer.getvalue()


STOP_WAIT = 2.0   # seconds a worker gets to exit at each step of stopping (stop message, SIGTERM, SIGKILL)
_READY = "ready"


def _serve(conn: Connection) -> None:
    """A worker's loop: (fn, item) in, (True, fn(item)) or (False, error text) out, until a None or a closed pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    try:
        import torch._inductor.config as inductor_config
        inductor_config.compile_threads = 1          # compile in the worker itself: no pool of compiler processes
    except ImportError:                              # pragma: no cover - torch without Inductor
        pass
    try:           # torch's progress bars (tqdm) lock with a thread lock: a multiprocessing one would outlive os._exit
        from tqdm import tqdm
        tqdm.set_lock(threading.RLock())
    except ImportError:                              # pragma: no cover - tqdm not installed
        pass
    conn.send_bytes(pickle.dumps(_READY))
    while True:
        try:
            task = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            task = None
        if task is None:                    # exit at once: tearing torch down takes seconds and is of no use here
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
        fn, item = task
        try:
            answer = (True, fn(item))
        except BaseException:                                     # sent back to the caller
            answer = (False, traceback.format_exc())
        conn.send_bytes(dumps(answer))


class WorkerPool:
    """``count`` worker processes, each with one pipe; :meth:`map` runs items on them in order."""

    def __init__(self, count: int):
        if count < 1:
            raise ValueError(f"count: expected >= 1 worker processes, got {count}")
        context = multiprocessing.get_context("spawn")
        self.pid = os.getpid()
        self.workers: list[tuple[multiprocessing.Process, Connection]] = []
        try:
            for _ in range(count):
                parent, child = context.Pipe()
                process = context.Process(target=_serve, args=(child,), daemon=True, name="dacr-ik-worker")
                process.start()
                child.close()
                self.workers.append((process, parent))
            for _, conn in self.workers:          # every worker has imported torch
                if pickle.loads(conn.recv_bytes()) != _READY:
                    raise RuntimeError("an IK worker process did not start")
        except BaseException:
            self.stop()
            raise

    @property
    def size(self) -> int:
        return len(self.workers)

    def map(self, fn: Callable, items: list) -> list:
        """[fn(item) for item in items], item i on worker i mod :attr:`size` (several items per worker in turn)."""
        out: list = [None] * len(items)
        for start in range(0, len(items), self.size):
            batch = list(enumerate(items[start:start + self.size]))
            for w, item in batch:
                self.workers[w][1].send_bytes(dumps((fn, item)))
            for w, _ in batch:
                try:
                    ok, value = pickle.loads(self.workers[w][1].recv_bytes())
                except EOFError:
                    raise RuntimeError(f"IK worker process {self.workers[w][0].pid} died "
                                       f"(exit code {self.workers[w][0].exitcode})") from None
                if not ok:
                    raise RuntimeError(f"an IK worker process failed:\n{value}")
                out[start + w] = value
        return out

    def stop(self) -> None:
        """Stop the workers: a stop message, then SIGTERM, then SIGKILL, each after up to :data:`STOP_WAIT` s."""
        for _, conn in self.workers:
            try:
                conn.send_bytes(pickle.dumps(None))
            except (OSError, ValueError):
                pass
        for step in ("stop", "terminate", "kill"):
            for process, _ in self.workers:
                if step != "stop" and process.is_alive():
                    getattr(process, step)()
            for process, _ in self.workers:
                process.join(STOP_WAIT)
        for _, conn in self.workers:
            conn.close()
        self.workers = []


_POOL: WorkerPool | None = None
_LOCK = threading.Lock()


def worker_pool(count: int) -> WorkerPool:
    """The process's pool of at least ``count`` workers: started on first use, restarted with more workers when a
    call needs more (or after a fork, in the child)."""
    global _POOL
    if _POOL is not None and _POOL.pid != os.getpid():
        _POOL = None                                   # a forked child: the workers are its parent's
    if _POOL is None or _POOL.size < count:
        if _POOL is not None:
            _POOL.stop()
        _POOL = WorkerPool(count)
    return _POOL


def run_in_processes(fn: Callable, items: list, count: int) -> list:
    """[fn(item) for item in items] on ``count`` worker processes (module docstring); one call at a time."""
    global _POOL
    with _LOCK:
        pool = worker_pool(count)
        try:
            return pool.map(fn, items)
        except BaseException:                          # interrupted, or a worker failed: no answer may linger
            pool.stop()
            _POOL = None
            raise


def process_cpu(_: object = None) -> float:
    """CPU time [s] of the calling process (of each worker, through ``run_in_processes(process_cpu, ...)``)."""
    return time.process_time()


@atexit.register
def stop_workers() -> None:
    """Stop the worker processes, if any (registered at exit)."""
    global _POOL
    if _POOL is not None and _POOL.pid == os.getpid():
        _POOL.stop()
    _POOL = None
