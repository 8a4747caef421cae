"""Run folders: where ``train.py`` keeps a run's files, so that nothing a user starts overwrites a run.

Layout (``runs_dir`` defaults to ``runs``)::

    <runs_dir>/<run_name>/version_<n>/      one folder per `fit` started without --ckpt_path (n = 0, 1, …)
        run.json                            recording id, run name, version, creation time, command line
        config.yaml                         the full CLI config of the fit
        checkpoints/last.ckpt               refreshed every epoch and on interruption (+ the best epochNNN.ckpt)
        rerun.rrd                           the fit's recording; each resume adds rerun_1.rrd, rerun_2.rrd, …
                                            with the same recording id (open them together: one recording)
        metrics.json                        test-split summary written after the fit
        test_<k>/metrics.json, rerun.rrd    one folder per later `train.py test` on this run's checkpoints

Folders are created with an exclusive ``mkdir``, so two runs started at once get two versions.
A trained model loads with :func:`load_model` from a run folder, a version folder or a ``.ckpt`` file.
No Lightning here: the functions handle paths, small JSON files and checkpoints read weights-only
(:func:`load_lightning_checkpoint` alone imports Lightning, to read a checkpoint through its LightningModule).
"""
from __future__ import annotations

import json
import re
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import torch

from .checks import load_torch_file, read_json_object, short_error
from .compositional import REQUIRED_HPARAMS, model_from_hparams
from .robot import RobotSpec

__all__ = [
    "ARCHITECTURE", "CHECKPOINT", "RUN_INFO", "SCHEDULE", "check_checkpoint_fits", "check_same_schedule",
    "checkpoint_run_dir", "checkpoint_task", "describe_model", "find_checkpoint", "free_path",
    "load_checkpoint_model", "load_lightning_checkpoint", "load_model", "new_numbered_dir", "numbered",
    "read_run_info", "versions", "write_run_info",
]

RUN_INFO = "run.json"
CHECKPOINT = "an FKModule/IKModule/SamplerModule checkpoint written by train.py or a Lightning Trainer"
MODULES = {"fk": "FKModule", "ik": "IKModule", "sampler": "SamplerModule"}   # task → its LightningModule
LAST = "last.ckpt"


def _numbered(parent: Path, prefix: str) -> list[tuple[int, Path]]:
    pattern = re.compile(rf"^{re.escape(prefix)}(\d+)$")
    if not parent.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in parent.iterdir() if p.is_dir() and (m := pattern.match(p.name))]
    return sorted(found)


def versions(run_root: str | Path) -> list[Path]:
    """The ``version_<n>`` folders of a run name's folder, by increasing ``n`` (empty if none)."""
    return numbered(run_root, "version_")


def numbered(parent: str | Path, prefix: str) -> list[Path]:
    """The ``<prefix><n>`` folders of ``parent`` (e.g. ``test_0``, ``test_1``), by increasing ``n``."""
    return [p for _, p in _numbered(Path(parent), prefix)]


def new_numbered_dir(parent: str | Path, prefix: str) -> Path:
    """Create and return ``parent/<prefix><n>`` for the smallest ``n`` above every existing one, with an exclusive
    ``mkdir`` (a concurrent caller gets the next number; an existing folder is never reused)."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    n = max((k for k, _ in _numbered(parent, prefix)), default=-1) + 1
    while True:
        path = parent / f"{prefix}{n}"
        try:
            path.mkdir()
            return path
        except FileExistsError:
            n += 1


def free_path(folder: str | Path, name: str) -> Path:
    """``folder/name`` if no such file exists, else the first free ``folder/<stem>_<k><suffix>`` (k = 1, 2, …):
    where a file a run wrote before stays untouched (a resumed fit's second config.yaml or metrics.json)."""
    path, stem, suffix = Path(folder) / name, Path(name).stem, Path(name).suffix
    k = 0
    while path.exists():
        k += 1
        path = Path(folder) / f"{stem}_{k}{suffix}"
    return path


def write_run_info(run_dir: str | Path, **fields: Any) -> dict[str, Any]:
    """Write ``run.json`` (a new ``recording_id`` and the creation time, plus ``fields``) into a new run
    folder; returns what was written. Refuses (ValueError) when the folder already has one."""
    path = Path(run_dir) / RUN_INFO
    info = {"recording_id": str(uuid.uuid4()), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join(sys.argv), **fields}
    try:
        with open(path, "x", encoding="utf-8") as f:
            json.dump(info, f, indent=2)
    except FileExistsError:
        raise ValueError(f"{path}: this run folder already has a run.json; a new run needs a new folder") from None
    return info


def read_run_info(run_dir: str | Path) -> dict[str, Any]:
    """The ``run.json`` of a run folder, or ``{}`` when it has none (e.g. a checkpoint copied elsewhere)."""
    path = Path(run_dir) / RUN_INFO
    if not path.is_file():
        return {}
    return read_json_object(path, "the run.json that train.py writes")


def checkpoint_run_dir(ckpt: str | Path) -> Path | None:
    """The run folder a checkpoint belongs to (``<run>/checkpoints/<file>.ckpt`` → ``<run>``), or ``None``
    when the file is not inside a folder that ``train.py`` made (no ``run.json`` beside ``checkpoints/``)."""
    ckpt = Path(ckpt)
    run = ckpt.parent.parent
    return run if ckpt.parent.name == "checkpoints" and (run / RUN_INFO).is_file() else None


def find_checkpoint(path: str | Path) -> Path:
    """The checkpoint a path names: a ``.ckpt`` file itself; a version folder → its ``checkpoints/last.ckpt``; a run
    name's folder → ``last.ckpt`` of its newest version that has one. FileNotFoundError says what was looked for."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no such file or folder; expected a .ckpt file, a run folder "
                                "(runs/<run_name>) or a version folder (runs/<run_name>/version_<n>)")
    for folder in (path, *reversed(versions(path))):               # a version folder, else the newest version
        if (folder / "checkpoints" / LAST).is_file():
            return folder / "checkpoints" / LAST
    raise FileNotFoundError(f"{path}: no checkpoints/{LAST} in it or in any version_<n> folder below it; "
                            "train a model first (train.py fit --config …)")


def checkpoint_task(ckpt: Path, raw: Any) -> str:
    """"fk" | "ik" | "sampler" of a loaded checkpoint dict; ValueError naming the file and the missing or wrong
    entry."""
    def bad(found: str) -> ValueError:
        return ValueError(f"{ckpt}: expected {CHECKPOINT}, found {found}")

    if not isinstance(raw, dict):
        raise bad(f"a torch file holding a {type(raw).__name__}, not a checkpoint dict")
    missing = [k for k in ("state_dict", "hyper_parameters", "pytorch-lightning_version") if k not in raw]
    if missing:
        raise bad(f"a dict without {missing} (keys: {sorted(map(str, raw))[:8]})")
    hparams, weights = raw["hyper_parameters"], raw["state_dict"]
    if not isinstance(hparams, dict) or "robot" not in hparams:
        raise bad(f"hyper_parameters without a robot spec: {str(hparams)[:200]}")
    try:
        RobotSpec.coerce(hparams["robot"])
    except (ValueError, OSError) as err:
        raise ValueError(f"{ckpt}: hyper_parameters.robot: {err}") from err
    for task, key in (("fk", "front.norm"), ("ik", "in_norm"), ("sampler", "target_norm")):
        if isinstance(weights, dict) and f"model.{key}.mean" in weights:
            return task
    raise bad("a state_dict without model.front.norm / model.in_norm / model.target_norm weights "
              f"(keys: {sorted(map(str, weights))[:8] if isinstance(weights, dict) else type(weights).__name__})")


def load_lightning_checkpoint(ckpt: str | Path, blob: Any = None):
    """(task "fk" | "ik" | "sampler", LightningModule in eval mode) of a checkpoint written by train.py or a Trainer
    (``blob``: its content, when already loaded weights-only). FileNotFoundError for a missing file, ValueError
    naming the file for anything else (not a torch file, truncated, not ours, weights that do not fit)."""
    from .training import FKModule, IKModule  # Lightning is imported only to read a checkpoint
    from .training_sampler import SamplerModule

    ckpt = Path(ckpt)
    task = checkpoint_task(ckpt, load_torch_file(ckpt, CHECKPOINT) if blob is None else blob)
    cls = {"fk": FKModule, "ik": IKModule, "sampler": SamplerModule}[task]
    try:
        return task, cls.load_from_checkpoint(ckpt, map_location="cpu").eval()
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        raise ValueError(f"{ckpt}: expected {CHECKPOINT}, found one that {cls.__name__} cannot load "
                         f"({short_error(err)})") from err


def load_checkpoint_model(ckpt: str | Path, blob: Any = None) -> tuple[str, torch.nn.Module]:
    """(task, the trained network in eval mode, float32) of a checkpoint, rebuilt from its hyper-parameters and
    weights without Lightning (:func:`~dacr_learn.compositional.model_from_hparams`), or through
    :func:`load_lightning_checkpoint` when the hyper-parameters lack part of the architecture
    (:data:`~dacr_learn.compositional.REQUIRED_HPARAMS`). ``blob`` and errors as :func:`load_lightning_checkpoint`."""
    ckpt = Path(ckpt)
    blob = load_torch_file(ckpt, CHECKPOINT) if blob is None else blob
    task = checkpoint_task(ckpt, blob)
    hparams = blob["hyper_parameters"]
    if not all(k in hparams for k in REQUIRED_HPARAMS[task]):
        task, module = load_lightning_checkpoint(ckpt, blob)
        return task, module.model
    try:
        model = model_from_hparams(task, RobotSpec.coerce(hparams["robot"]), hparams)
        prefix = "model."
        model.load_state_dict({k[len(prefix):]: v for k, v in blob["state_dict"].items() if k.startswith(prefix)})
    except (KeyError, RuntimeError, TypeError, ValueError) as err:
        name = MODULES[task]
        raise ValueError(f"{ckpt}: expected {CHECKPOINT}, found one whose weights and hyper-parameters {name} "
                         f"cannot load ({short_error(err)})") from err
    return task, model.eval()


# hyper-parameters that decide what a checkpoint's weights compute (not how they were trained)
ARCHITECTURE = ("features", "structure", "context", "width", "depth", "activation", "rotation", "transforms", "bins")


def describe_model(kind: str, hparams: dict[str, Any]) -> str:
    """One phrase naming a model: its class, robot (name, joints) and architecture hyper-parameters."""
    try:
        spec = RobotSpec.coerce(hparams.get("robot"))
        segments = f"{spec.num_segments} segment" + ("s" if spec.num_segments > 1 else "")
        robot_text = f"robot {spec.name!r} ({segments}, {spec.num_joints} joints)"
    except (ValueError, OSError, TypeError):
        robot_text = f"robot {hparams.get('robot')!r}"
    arch = ", ".join(f"{k} {hparams[k]}" for k in ARCHITECTURE if k in hparams)
    return f"{kind} for {robot_text}, {arch}"


def check_checkpoint_fits(ckpt: str | Path, blob: Any, kind: str, hparams: dict[str, Any],
                          state_dict: dict[str, torch.Tensor]) -> None:
    """ValueError (one line, naming both) unless the checkpoint ``ckpt`` (``blob``: its loaded content) holds a
    model of class ``kind`` for the same robot, with the same architecture hyper-parameters and weight shapes as
    the model the config builds (``kind``, ``hparams``, ``state_dict``: that model's)."""
    saved_kind = MODULES[checkpoint_task(Path(ckpt), blob)]
    saved, weights = blob["hyper_parameters"], blob["state_dict"]
    same = (saved_kind == kind and saved.get("robot") == hparams.get("robot")
            and all(saved.get(k) == hparams.get(k) for k in ARCHITECTURE)
            and {k: tuple(v.shape) for k, v in weights.items()}
            == {k: tuple(v.shape) for k, v in state_dict.items()})
    if not same:
        raise ValueError(f"checkpoint {ckpt} holds an {describe_model(saved_kind, saved)}; the config asks for an "
                         f"{describe_model(kind, hparams)}: pass a checkpoint of this model, or start a new run "
                         "without --ckpt_path")


# settings that fix the number of optimiser steps, over which the one-cycle learning-rate schedule runs
SCHEDULE = (("trainer", "max_epochs"), ("trainer", "max_steps"), ("trainer", "accumulate_grad_batches"),
            ("data", "n_train"), ("data", "batch_size"))


def check_same_schedule(ckpt: str | Path, blob: Any, config: dict[str, Any]) -> None:
    """ValueError (one line, naming both values) when a fit resumed from ``ckpt`` (``blob``: its loaded content)
    would change the length of the run whose learning-rate schedule the checkpoint carries (:data:`SCHEDULE`).
    ``config``: the CLI config of the resumed fit as a nested dict. A checkpoint without the CLI config passes."""
    import yaml

    text = blob.get("dacr_config") if isinstance(blob, dict) else None
    saved = yaml.safe_load(text) if isinstance(text, str) else None
    if isinstance(saved, dict) and isinstance(saved.get("fit"), dict):
        saved = saved["fit"]                          # the dump of the whole CLI: {fit: {...}}
    if not isinstance(saved, dict):
        return
    for group, key in SCHEDULE:
        before, now = (saved.get(group) or {}).get(key), (config.get(group) or {}).get(key)
        if before != now:
            raise ValueError(f"checkpoint {ckpt} was trained with {group}.{key} {before}; the config asks for {now}: "
                             "a resumed fit keeps the run's learning-rate schedule, so resume with the run's own "
                             "settings, or start a new run without --ckpt_path")


def load_model(path: str | Path, dtype: torch.dtype = torch.float32, blob: Any = None) -> torch.nn.Module:
    """The trained network of a ``train.py`` run, in eval mode, ready to predict.

    ``path``: a run folder (``runs/<run_name>``: its newest version), a version folder
    (``runs/<run_name>/version_<n>``) or a checkpoint file; ``dtype``: of the returned model's parameters;
    ``blob``: the file's content when the caller has loaded it (weights-only, e.g.
    :func:`~dacr_learn.hardware.deploy.checkpoint.read_model_file`), ``path`` then names that file.

    Returns an ``nn.Module`` with ``.spec`` (its :class:`~dacr_learn.robot.RobotSpec`) and ``.task``: "fk" (joint
    lengths (..., N) [m] → tip poses (..., 4, 4) [m]), "ik" (the reverse) or "sampler"
    (:class:`~dacr_learn.sampler.ClarkeSampler`: ``sample_features(target, count)`` → (B, count, D) float64).
    FK / IK models cast floating inputs to ``dtype``; an FK model raises a ValueError for joint lengths far outside
    the robot's limits (millimetres instead of metres). FileNotFoundError: nothing at ``path``; ValueError: not a
    checkpoint of an FK / IK module (the message names the file).
    """
    task, model = load_checkpoint_model(find_checkpoint(path), blob)
    model = model.to(dtype).eval()
    model.task = task
    if task in ("fk", "ik"):
        model.register_forward_pre_hook(_FriendlyInput(task))
    return model


def _longest_joint_length(spec: RobotSpec) -> float:
    """An upper bound [m] of any joint length inside the robot's limits: every segment at its longest, bent and
    twisted to its limits at its outermost joint (a tendon passes at most every segment)."""
    total = 0.0
    for seg in spec.segments:
        longest = seg.length_range[1] if seg.length_range else seg.length
        twist = max(map(abs, seg.twist_range)) if seg.twist_range else 0.0
        total += longest + max(seg.joint_radii) * (seg.bend + twist)
    return total


JOINT_UNIT_FACTOR = 2.0    # joint lengths beyond this many times the longest possible one: not metres


class _FriendlyInput:
    """Forward pre-hook of :func:`load_model`'s FK / IK models: floating inputs of another dtype are cast to the
    model's; an FK model refuses joint lengths far outside the robot's limits (millimetres instead of metres).
    Skipped while tracing and under torch.func transforms, like check_tensor."""

    def __init__(self, task: str):
        self.task = task

    def __call__(self, module: torch.nn.Module, args: tuple) -> tuple | None:
        if not args or not isinstance(args[0], torch.Tensor) or not args[0].is_floating_point():
            return None
        x = args[0]
        dtype = next((p.dtype for p in module.parameters() if p.is_floating_point()), x.dtype)
        if x.dtype != dtype:
            x = x.to(dtype)
        if (self.task == "fk" and x.numel() and not torch.compiler.is_compiling()
                and not torch._C._functorch.is_functorch_wrapped_tensor(x)):
            spec = module.spec                 # read at each call: a transferred copy has another robot
            longest, n = _longest_joint_length(spec), spec.num_length_joints
            worst = float(x[..., :n].detach().abs().amax()) if x.shape[-1] >= n else 0.0
            if worst > JOINT_UNIT_FACTOR * longest:
                raise ValueError(
                    f"joint vector: expected joint lengths in metres, at most {longest:.3g} m for robot "
                    f"{spec.name!r} within its limits, got {worst:.4g} (millimetres? divide by 1000)")
        return (x, *args[1:])
