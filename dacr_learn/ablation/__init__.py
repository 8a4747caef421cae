"""Ablation study "Clarke features vs raw joint lengths" (docs/ablation.md).

    python -m dacr_learn.ablation --config configs/ablation/default.yaml --out runs/ablation_full --workers 2
    python -m dacr_learn.ablation --config configs/ablation/default.yaml --quick --out runs/ablation_quick

Writes ``<out>/results.csv`` (one row per run and test condition, appended and flushed as each
training finishes, so an interrupted grid resumes where it stopped), ``summary.md``, one PNG per
task and condition, and ``ablation.rrd``. The command line: :mod:`dacr_learn.cli.ablation`.
"""
from .runner import COLUMNS, Job, conditions, evaluate, load_config, make_jobs, run_job

__all__ = ["COLUMNS", "Job", "conditions", "evaluate", "load_config", "make_jobs", "run_job"]
