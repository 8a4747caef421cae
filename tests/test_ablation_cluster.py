"""Ablation runner on a Dask distributed cluster (``--cluster``): a local 2-worker cluster started here,
one worker killed while it runs a job; the job runs again elsewhere and the results file holds
exactly one row per (job, condition). Skipped when the optional extra ``cluster`` is not installed."""
from __future__ import annotations

import csv
import os
import signal
import threading
import time
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, no_ablation_reports

distributed = pytest.importorskip("distributed", reason='Dask distributed not installed: pip install -e ".[cluster]"')

import psutil  # noqa: E402  (a dependency of distributed)

import dacr_learn.cli.ablation as ablation_cli  # noqa: E402
from dacr_learn.ablation import load_config, make_jobs, runner  # noqa: E402
from dacr_learn.ablation.cluster import connect, portable_config  # noqa: E402
from dacr_learn.cli.ablation import main  # noqa: E402


def tiny_config(tmp_path: Path) -> Path:
    """Two FK jobs of one robot, a few seconds each (slow enough to be caught mid-job)."""
    cfg = yaml.safe_load((ROOT / "configs" / "ablation" / "default.yaml").read_text())
    cfg.pop("quick")
    cfg.update(robots={"type1": "configs/robots/type1.yaml"}, tasks=["fk"], features=["clarke"], n_train=[500, 1000],
               seeds=[0], model={"width": 16, "depth": 1, "activation": "silu", "lr": 3e-3},
               train={"steps": 60, "batch_size": 64}, test={"n": 200, "seed": 5}, transfer=None)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


class WorkerKiller(threading.Thread):
    """Kills (SIGKILL) the process of the first worker seen running a task; its nanny restarts it."""

    def __init__(self, address: str):
        super().__init__(daemon=True)
        self.client = distributed.Client(address)
        self.pids = self.client.run(os.getpid)            # worker address -> pid
        self.killed: tuple[str, list] | None = None
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set() and self.killed is None:
            busy = {w: keys for w, keys in self.client.processing().items() if keys}
            if busy:
                worker, keys = next(iter(busy.items()))
                time.sleep(0.3)                           # inside the job (Lightning set-up + training)
                os.kill(self.pids[worker], signal.SIGKILL)
                self.killed = (worker, list(keys))
            time.sleep(0.05)


def live_children() -> set[int]:
    """PIDs of this process's live descendants, except multiprocessing's resource tracker (it lives as
    long as this interpreter, whoever started it)."""
    out = set()
    for p in psutil.Process().children(recursive=True):
        try:
            if p.status() != psutil.STATUS_ZOMBIE and "resource_tracker" not in " ".join(p.cmdline()):
                out.add(p.pid)
        except psutil.NoSuchProcess:
            pass
    return out


@pytest.mark.slow
def test_cluster_run_survives_a_killed_worker(tmp_path, monkeypatch):
    monkeypatch.setattr(ablation_cli, "write_reports", no_ablation_reports)      # the rows are checked, not the plots
    config, before = tiny_config(tmp_path), live_children()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50) as cluster:
        killer = WorkerKiller(cluster.scheduler_address)
        killer.start()
        try:
            result = main(["--config", str(config), "--out", str(tmp_path / "out"), "--cluster",
                           cluster.scheduler_address, "--no-progress"])
        finally:
            killer.stop.set()
            killer.join(5)
            killer.client.close()
    assert killer.killed is not None, "no worker was seen running a job"
    deadline = time.monotonic() + 10
    while live_children() - before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not live_children() - before, "the cluster left processes running"
    cfg = load_config(config)
    jobs = make_jobs(cfg)
    assert result["ran"] == len(jobs) == 2
    with (tmp_path / "out" / "results.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    keys = [(*runner.row_key(r), r["condition"]) for r in rows]
    expected = {(*j.key, c) for j in jobs for c in runner.conditions(cfg, j)}
    assert len(keys) == len(set(keys))                # no row written twice ...
    assert set(keys) == expected                      # ... nor lost
    assert all(float(r["pos_err_mean_mm"]) > 0 for r in rows)


def test_portable_config_ships_robot_specs():
    cfg = portable_config(load_config(ROOT / "configs" / "ablation" / "default.yaml", quick=True))
    assert all(isinstance(v, dict) and "segments" in v for v in cfg["robots"].values())
    assert isinstance(cfg["transfer"]["to"], dict)
    assert runner.robot_spec(cfg["robots"]["type0_n4"]) == runner.robot_spec("configs/robots/type0_n4.yaml")


def test_connect_without_dask_names_the_extra(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_distributed(name, *args, **kwargs):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError("No module named 'distributed'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_distributed)
    with pytest.raises(SystemExit, match=r"\.\[cluster\]"):
        connect("tcp://127.0.0.1:1")
