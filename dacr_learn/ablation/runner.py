"""Grid runner of the ablation "Clarke features vs raw joint lengths": config, jobs, one run, resume.

One *job* = one training (robot, task, features, n_train, seed, structure) through the LightningModules of
``train.py`` for a fixed number of steps, evaluated on fixed test sets, one CSV row per test-time *condition*
(:func:`conditions`; what each is: docs/ablation.md, "Protocol").

``data: {source: cosserat, cosserat: {...}, cache_dir: DIR}`` (optional; default CC samples) trains and tests on
Cosserat-rod datasets (:mod:`dacr_learn.data.cosserat`), cached under DIR; only ``clean``, and FK rows gain
``cc_pos_err_mean_pct``: the CC model on the same test set.
"""
from __future__ import annotations

import copy
import csv
import json
import logging
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import lightning.pytorch as pl
import torch
from torch import Tensor

from ..checks import read_yaml
from ..console import quiet_third_party_warnings
from ..data import SamplerOptions, generate
from ..data import cosserat as cosserat_dataset
from ..metrics import pose_errors, summarize
from ..robot import RobotSpec
from ..training import FKModule, IKModule, ik_errors

ROOT = Path(__file__).resolve().parents[2]
COLUMNS = ["robot", "task", "features", "structure", "n_train", "condition", "seed", "pos_err_mean_mm",
           "pos_err_mean_pct", "rot_err_mean_deg", "joint_err_mean_mm", "constraint_residual_max_m", "train_seconds",
           "steps", "n_test", "note", "cc_pos_err_mean_pct"]
KEY = ("robot", "task", "features", "n_train", "seed", "structure")
STRUCTURES = ("monolithic", "compositional")
METRICS = ("pos_err_mean_mm", "pos_err_mean_pct", "rot_err_mean_deg", "joint_err_mean_mm", "constraint_residual_max_m")
MODULES = {"fk": FKModule, "ik": IKModule}
# Settings that change the numbers of a finished row: resuming with different values is refused.
FROZEN_KEYS = ("model", "model_by_task", "model_by_structure", "train", "test", "conditions", "transfer", "data")


@dataclass(frozen=True)
class Job:
    robot: str
    task: str
    features: str
    n_train: int
    seed: int
    structure: str = "monolithic"

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(str(getattr(self, k)) for k in KEY)


def row_key(row: dict) -> tuple[str, ...]:
    """The job key of a CSV row (rows written before the structure axis existed are monolithic)."""
    return tuple(row.get(k) or ("monolithic" if k == "structure" else "") for k in KEY)


def resolve_path(path: str | Path) -> Path:
    """A config path as given if it exists (relative to the cwd), else relative to the repository root."""
    p = Path(path)
    return p if p.exists() or p.is_absolute() else ROOT / p


def robot_spec(entry: str | dict) -> RobotSpec:
    """A robot of the config: a YAML path (see :func:`resolve_path`) or a RobotSpec dict."""
    return RobotSpec.from_dict(entry) if isinstance(entry, dict) else RobotSpec.from_yaml(resolve_path(entry))


def load_config(path: str | Path, quick: bool = False) -> dict:
    """The ablation config (YAML); with ``quick`` the keys of its ``quick:`` section replace the others.
    Every robot it names is read here, so a broken robot file fails before the first job."""
    cfg = read_yaml(resolve_path(path), "an ablation config YAML (docs/ablation.md)")
    if not isinstance(cfg, dict):
        raise ValueError(f"{path}: expected an ablation config (a YAML mapping), found {type(cfg).__name__}")
    overrides = cfg.pop("quick", None) or {}
    if quick:
        cfg.update(overrides)
    for key in ("robots", "tasks", "features", "n_train", "seeds", "model", "train", "test", "conditions"):
        if key not in cfg:
            raise ValueError(f"ablation config {path}: missing key {key!r}")
    cfg.setdefault("structures", ["monolithic"])
    bad_structures = set(cfg["structures"]) - set(STRUCTURES)
    if bad_structures:
        raise ValueError(f"ablation config {path}: structures: unknown {sorted(bad_structures)}, "
                         f"expected a subset of {list(STRUCTURES)}")
    data = cfg.get("data") or {}
    if data.get("source", "cc") not in ("cc", "cosserat") or set(data) - {"source", "cosserat", "cache_dir"}:
        raise ValueError(f"ablation config {path}: data: expected source 'cc' or 'cosserat' and the keys cosserat, "
                         f"cache_dir, got {data}")
    if data.get("source") == "cosserat":
        cosserat_dataset.CosseratOptions.from_dict(data.get("cosserat"))     # bad options fail before the first job
    bad = set(cfg["tasks"]) - set(MODULES)
    if bad:
        raise ValueError(f"ablation config {path}: tasks: unknown {sorted(bad)}, "
                         f"expected a subset of {sorted(MODULES)}")
    robots = {f"robots.{name}": entry for name, entry in cfg["robots"].items()}
    if (cfg.get("transfer") or {}).get("to") is not None:
        robots["transfer.to"] = cfg["transfer"]["to"]
    for key, entry in robots.items():
        try:
            robot_spec(entry)
        except (ValueError, FileNotFoundError) as err:
            raise type(err)(f"ablation config {path}: {key}: {err}") from err
    return cfg


def make_jobs(cfg: dict) -> list[Job]:
    """Every training of the grid; seeds outermost so a stopped grid has complete early seeds. The ``structures``
    axis applies to FK with Clarke features only (a compositional model needs per-segment features; no IK)."""
    return [Job(r, t, f, int(n), int(s), st) for s in cfg["seeds"] for n in cfg["n_train"] for r in cfg["robots"]
            for t in cfg["tasks"] for f in cfg["features"] for st in cfg.get("structures", ["monolithic"])
            if st == "monolithic" or (t == "fk" and f == "clarke")]


def conditions(cfg: dict, job: Job) -> list[str]:
    """Names of the test-time conditions (CSV rows) of a job."""
    if is_cosserat(cfg):
        return ["clean"]
    names = ["clean", "joint_noise", "offset"] if job.task == "fk" else ["clean", "pose_noise"]
    transfer = cfg.get("transfer")
    if transfer and job.robot == transfer["from"]:
        names.append(transfer.get("name", "transfer"))
    return names


# Data: training stream with a fixed number of steps, fixed test sets
class StepBatches:
    """Exactly ``steps`` training batches, drawn epoch by epoch from reshuffled permutations."""

    def __init__(self, data: dict[str, Tensor], steps: int, batch_size: int, seed: int):
        self.q, self.pose = data["q"], data["pose"]
        self.steps, self.batch_size, self.seed = steps, min(batch_size, len(data["q"])), seed

    def __len__(self) -> int:
        return self.steps

    def __iter__(self):
        g, n, order, i = torch.Generator().manual_seed(self.seed), len(self.q), None, 0
        for _ in range(self.steps):
            if order is None or i + self.batch_size > n:
                order, i = torch.randperm(n, generator=g), 0
            idx, i = order[i:i + self.batch_size], i + self.batch_size
            yield {"q": self.q[idx], "pose": self.pose[idx], "valid": torch.ones(len(idx), dtype=torch.bool)}


class StepDataModule(pl.LightningDataModule):
    """In-memory training data with ``splits["train"]`` (the modules fit their normalisation on it)."""

    def __init__(self, data: dict[str, Tensor], steps: int, batch_size: int, seed: int):
        super().__init__()
        self.splits = {"train": data}
        self.steps, self.batch_size, self.seed = steps, batch_size, seed

    def train_dataloader(self):
        return StepBatches(self.splits["train"], self.steps, self.batch_size, self.seed)


def test_options(cfg: dict, condition: str) -> SamplerOptions:
    c = cfg["conditions"]
    return {"joint_noise": SamplerOptions(joint_noise=c["joint_noise"]),
            "offset": SamplerOptions(common_offset=c["offset"]),
            "pose_noise": SamplerOptions(pose_noise_pos=c["pose_noise_pos"], pose_noise_rot=c["pose_noise_rot"]),
            }.get(condition, SamplerOptions())


def is_cosserat(cfg: dict) -> bool:
    return (cfg.get("data") or {}).get("source", "cc") == "cosserat"


def dataset(cfg: dict, spec: RobotSpec, n: int, seed: int, options: SamplerOptions | None = None):
    """n samples of the config's source: CC (generated with ``options``) or Cosserat (cached in
    ``data.cache_dir``)."""
    if not is_cosserat(cfg):
        return generate(spec, n, seed, options or SamplerOptions())
    data = cfg["data"]
    cache = resolve_path(data.get("cache_dir", "data/synthetic/ablation_cosserat")) / f"{spec.name}_n{n}_seed{seed}"
    return cosserat_dataset.generate_or_load(cache, spec, n, seed,
                                             cosserat_dataset.CosseratOptions.from_dict(data.get("cosserat")))


def test_set(cfg: dict, spec: RobotSpec, condition: str) -> dict[str, Tensor]:
    """The fixed test set of a robot and condition: the same samples for every run (and seed)."""
    options = None if is_cosserat(cfg) else test_options(cfg, condition)
    return dataset(cfg, spec, int(cfg["test"]["n"]), int(cfg["test"]["seed"]), options)


# One job
def model_kwargs(cfg: dict, task: str, structure: str = "monolithic") -> dict:
    """Keyword arguments of a job's module: ``model``, then ``model_by_task[task]``, then (for a
    structure other than monolithic) ``model_by_structure[structure]`` and ``structure`` itself."""
    kwargs = {**cfg["model"], **(cfg.get("model_by_task") or {}).get(task, {})}
    if structure != "monolithic":
        kwargs.update({**(cfg.get("model_by_structure") or {}).get(structure, {}), "structure": structure})
    return kwargs


def build_module(cfg: dict, task: str, robot: str | dict, features: str,
                 structure: str = "monolithic") -> pl.LightningModule:
    return MODULES[task](robot=robot, features=features, **model_kwargs(cfg, task, structure))


@torch.no_grad()
def evaluate(module: pl.LightningModule, task: str, data: dict[str, Tensor]) -> dict[str, float]:
    """Summary metrics of a trained module on a test set, errors against the clean targets: FK the pose of ``q``
    vs ``pose_clean``; IK the CC pose of the joints predicted for ``pose`` vs ``pose_clean``, joints vs ``q_clean``."""
    module.eval()
    model, spec = module.model, module.spec
    if task == "fk":
        errors = pose_errors(model(data["q"]), data["pose_clean"])
    else:
        errors = ik_errors(model, spec, data["pose"], data["pose_clean"], data["q_clean"])
    return summarize(errors, spec.total_length)


def transferred(cfg: dict, module: pl.LightningModule, job: Job, target: RobotSpec):
    """The trained network and normalisation of ``module`` behind the Clarke layers of ``target``."""
    new = build_module(cfg, job.task, target.to_dict(), job.features, job.structure)
    state = {k: v for k, v in module.state_dict().items() if ".encoder." not in k and ".decoder." not in k}
    missing, unexpected = new.load_state_dict(state, strict=False)
    if unexpected or any(".encoder." not in k and ".decoder." not in k for k in missing):
        raise RuntimeError(f"transfer: unexpected state-dict mismatch: missing {missing}, unexpected {unexpected}")
    return new


def quiet_lightning() -> None:
    """Silence the Trainers these studies build inside each job: Lightning's INFO lines, the third-party
    warnings of :func:`dacr_learn.console.quiet_third_party_warnings`, and Lightning's two warnings about
    what the runner does on purpose (each filter: that one message from the module that issues it)."""
    for name in ("lightning.pytorch", "lightning.fabric", "lightning"):
        logging.getLogger(name).setLevel(logging.ERROR)
    quiet_third_party_warnings()
    # the runner trains without validation (StepDataModule has no val_dataloader)
    warnings.filterwarnings("ignore", message="You defined a `validation_step` but have no `val_dataloader`",
                            category=UserWarning, module=r"lightning\.pytorch\.trainer\.configuration_validator\Z")
    # the training tensors are in memory: loader worker processes would only add start-up time
    warnings.filterwarnings("ignore", message=r"The '\w+' does not have many workers", category=UserWarning,
                            module=r"lightning\.pytorch\.trainer\.connectors\.data_connector\Z")


def fit(cfg: dict, job: Job, spec: RobotSpec) -> tuple[pl.LightningModule, float]:
    """Train one module for ``cfg.train.steps`` steps; returns it and the fit time [s]."""
    quiet_lightning()
    steps, bs = int(cfg["train"]["steps"]), int(cfg["train"]["batch_size"])
    data = dataset(cfg, spec, job.n_train, seed=1 + job.seed)
    pl.seed_everything(job.seed, verbose=False)
    module = build_module(cfg, job.task, spec.to_dict(), job.features, job.structure)
    return module, train_steps(module, data, steps, bs, job.seed)


def train_steps(module: pl.LightningModule, data: dict[str, Tensor], steps: int, batch_size: int, seed: int) -> float:
    """Train ``module`` for ``steps`` steps of ``batch_size`` samples of ``data`` on the CPU (no logger, checkpoint
    or validation: :class:`StepDataModule`); returns the fit time [s]."""
    trainer = pl.Trainer(max_steps=steps, max_epochs=1, accelerator="cpu", devices=1, logger=False,
                         enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                         limit_val_batches=0, num_sanity_val_steps=0)
    start = time.perf_counter()
    trainer.fit(module, datamodule=StepDataModule(data, steps, batch_size, seed=seed))
    return time.perf_counter() - start


def run_job(cfg: dict, job: Job) -> list[dict]:
    """Train one job and evaluate every condition: the job's CSV rows."""
    spec = robot_spec(cfg["robots"][job.robot])
    module, seconds = fit(cfg, job, spec)
    rows = []
    for cond in conditions(cfg, job):
        row = {**{k: getattr(job, k) for k in KEY}, "condition": cond, "train_seconds": round(seconds, 3),
               "steps": cfg["train"]["steps"], "n_test": cfg["test"]["n"], "note": ""}
        transfer = cfg.get("transfer") or {}
        if cond == transfer.get("name", "transfer") and job.robot == transfer.get("from"):
            target = robot_spec(transfer["to"])
            if job.features != "clarke":
                row["note"] = (f"raw model takes {spec.num_joints} joint lengths; the {target.num_joints}-joint "
                               f"robot {target.name} cannot be fed (nor, for IK, produced)")
                summary = {}
            else:
                summary = evaluate(transferred(cfg, module, job, target), job.task,
                                   test_set(cfg, target, "clean"))
                row["note"] = f"trained on {spec.name}, evaluated on {target.name} through its Clarke layers"
        else:
            test = test_set(cfg, spec, cond)
            summary = evaluate(module, job.task, test)
            if is_cosserat(cfg) and job.task == "fk":
                row["cc_pos_err_mean_pct"] = cosserat_dataset.cc_baseline(spec, test["q"], test["pose"])[
                    "cc_pos_err_mean_pct"]
        row.update({k: summary.get(k, math.nan) for k in METRICS})
        rows.append(row)
    return rows


# Results file: append-and-flush, resume
def read_rows(csv_path: Path) -> list[dict]:
    """Rows of a results CSV (a truncated last line, e.g. after a kill, is dropped)."""
    if not csv_path.is_file():
        return []
    with csv_path.open(newline="") as f:
        return [r for r in csv.DictReader(f) if None not in r.values() and None not in r]


def finished_rows(cfg: dict, csv_path: Path) -> tuple[list[dict], set[tuple[str, ...]]]:
    """Rows of jobs whose every condition row is present, and the keys of those jobs."""
    rows = read_rows(csv_path)
    by_key: dict[tuple[str, ...], list[dict]] = {}
    for r in rows:
        by_key.setdefault(row_key(r), []).append(r)
    done = set()
    for job in make_jobs(cfg):
        got = {r["condition"] for r in by_key.get(job.key, [])}
        if set(conditions(cfg, job)) <= got:
            done.add(job.key)
    grid = {j.key for j in make_jobs(cfg)}
    keep = [r for r in rows if row_key(r) in done or row_key(r) not in grid]
    return keep, done


def rewrite(csv_path: Path, rows: list[dict]) -> None:
    """Atomically replace the CSV with ``rows`` (drops partial jobs before a resume)."""
    tmp = csv_path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(csv_path)


def append_rows(csv_path: Path, rows: list[dict]) -> None:
    """Append the rows of one finished job and flush them to disk at once."""
    with csv_path.open("a", newline="") as f:
        csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore").writerows(rows)
        f.flush()
        os.fsync(f.fileno())


def check_frozen(cfg: dict, out: Path) -> None:
    """Write ``config.json``; refuse to resume into a directory produced with other settings."""
    path = out / "config.json"
    frozen = {k: cfg.get(k) for k in FROZEN_KEYS}
    if path.is_file():
        old = json.loads(path.read_text())
        old_frozen = {k: old.get(k) for k in FROZEN_KEYS}
        if json.loads(json.dumps(frozen)) != old_frozen:
            raise SystemExit(f"{out} holds results of different settings ({path}); use another --out. "
                             f"Was {old_frozen}, now {frozen}")
    path.write_text(json.dumps(copy.deepcopy(cfg), indent=2))
