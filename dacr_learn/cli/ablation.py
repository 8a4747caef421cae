"""Command line of the ablation runner: run the pending jobs of a grid (optionally in worker processes or on a
Dask distributed cluster, ``--cluster ADDRESS``; see :mod:`dacr_learn.ablation.cluster`)."""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
from concurrent.futures import FIRST_COMPLETED, Executor, ProcessPoolExecutor, wait
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..ablation import runner
from ..ablation.cluster import run_job_one_thread
from ..ablation.report import write_reports


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m dacr_learn.ablation", description=__doc__)
    p.add_argument("--config", default="configs/ablation/default.yaml", help="ablation YAML")
    p.add_argument("--out", required=True, help="output directory (results.csv, summary.md, *.png, ablation.rrd)")
    p.add_argument("--quick", action="store_true", help="the reduced grid of the config's quick: section")
    p.add_argument("--workers", type=int, default=1, help="worker processes (each uses one torch thread)")
    p.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="run the jobs on the Dask distributed scheduler at ADDRESS (e.g. tcp://host:8786) instead of "
                        "local processes; needs the optional extra: pip install -e '.[cluster]'")
    p.add_argument("--report-only", action="store_true", help="only rebuild the reports from results.csv")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p.parse_args(argv)


def _run_in_process(cfg, jobs, sink) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for job in jobs:
            sink(runner.run_job(cfg, job))
    finally:
        torch.set_num_threads(threads)


def _run_with_executor(executor: Executor, fn, cfg, jobs, sink, in_flight: int) -> None:
    """Keep ``in_flight`` jobs submitted to ``executor``; rows are written by this process (``sink``)
    exactly once per finished job, whichever worker ran it and however often it was retried."""
    queue, running = list(jobs), set()
    try:
        while queue or running:
            while queue and len(running) < in_flight:
                running.add(executor.submit(fn, cfg, queue.pop(0)))
            finished, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                sink(fut.result())
    except BaseException:
        for fut in running:
            fut.cancel()
        raise


def _run_in_pool(cfg, jobs, sink, workers: int) -> None:
    """Local worker processes (spawned, one torch thread each)."""
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        _run_with_executor(pool, run_job_one_thread, cfg, jobs, sink, workers)


def _run_on_cluster(cfg, jobs, sink, address: str) -> None:
    """Every pending job submitted at once to the Dask scheduler at ``address`` (it queues them, and
    workers that join later take their share)."""
    from ..ablation.cluster import connect, portable_config

    client = connect(address)
    try:
        executor = client.get_executor(pure=False)
        _run_with_executor(executor, run_job_one_thread, portable_config(cfg), jobs, sink, max(1, len(jobs)))
    finally:
        client.close()


def main(argv=None) -> dict:
    """Run the pending jobs of the grid and write the reports; returns {"ran": n, "skipped": n, "out": path}."""
    args = parse_args(argv)
    cfg = runner.load_config(args.config, quick=args.quick)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "results.csv"
    ran = skipped = 0
    if not args.report_only:
        runner.check_frozen(cfg, out)
        keep, done = runner.finished_rows(cfg, csv_path)
        runner.rewrite(csv_path, keep)                       # drops the rows of a job cut off mid-write
        jobs = runner.make_jobs(cfg)
        pending = [j for j in jobs if j.key not in done]
        skipped = len(jobs) - len(pending)
        bar = tqdm(total=len(jobs), initial=skipped, unit="run", desc="ablation", dynamic_ncols=True,
                   disable=args.no_progress, file=sys.stderr)

        def sink(rows):
            nonlocal ran
            runner.append_rows(csv_path, rows)
            ran += 1
            r = rows[0]
            bar.set_postfix_str(f"{r['robot']} {r['task']} {r['features']} n={r['n_train']} s={r['seed']}")
            bar.update(1)

        try:
            if args.cluster:
                _run_on_cluster(cfg, pending, sink, args.cluster)
            elif args.workers <= 1:
                _run_in_process(cfg, pending, sink)
            else:
                _run_in_pool(cfg, pending, sink, args.workers)
        finally:
            bar.close()
    title = f"Ablation Clarke vs raw ({'quick' if args.quick else 'full'} grid, {Path(args.config).name})"
    reports = write_reports(runner.read_rows(csv_path), out, list(cfg["robots"]), title)
    print(f"{ran} runs done, {skipped} already finished; results in {csv_path}, {reports['summary']}, "
          f"{len(reports['plots'])} plots, {reports['rrd']}")
    return {"ran": ran, "skipped": skipped, "out": out, **reports}
