"""Run the ablation's jobs on a Dask distributed cluster (optional extra ``cluster``; how to start the scheduler
and the workers: docs/ablation.md, "On a cluster").

The workers need the same ``dacr_learn`` installed; robot YAMLs are shipped as spec dicts. Jobs go through
``Client.get_executor()`` (a ``concurrent.futures.Executor``, like the local pool). A worker that dies loses
only that attempt (the scheduler retries it, then fails with ``KilledWorker``); rows are written by the
submitting process once per finished job.
"""
from __future__ import annotations

import copy

import torch

from .runner import Job, robot_spec, run_job

INSTALL_HINT = 'pip install -e ".[cluster]"  (or: pip install "dask[distributed]")'


def connect(address: str):
    """A ``distributed.Client`` connected to the scheduler at ``address`` (e.g. ``tcp://host:8786``)."""
    try:
        from distributed import Client
    except ImportError as err:
        raise SystemExit(f"--cluster {address}: Dask distributed is not installed ({err}); "
                         f"install the optional extra: {INSTALL_HINT}") from err
    return Client(address)


def portable_config(cfg: dict) -> dict:
    """A copy of ``cfg`` whose robot paths (``robots`` values, ``transfer.to``) are replaced by
    RobotSpec dicts, so a worker on another machine needs no ``configs/`` directory."""
    out = copy.deepcopy(cfg)
    out["robots"] = {name: robot_spec(entry).to_dict() for name, entry in cfg["robots"].items()}
    if out.get("transfer"):
        out["transfer"]["to"] = robot_spec(out["transfer"]["to"]).to_dict()
    return out


def run_job_one_thread(cfg: dict, job: Job) -> list[dict]:
    """:func:`runner.run_job` with one torch thread (a Dask worker thread runs one job at a time)."""
    torch.set_num_threads(1)
    return run_job(cfg, job)
