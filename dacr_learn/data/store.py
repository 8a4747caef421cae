"""Dataset folders: ``tensors.pt`` + ``meta.json`` (robot, source, options, seed, sha256), written atomically and
refused on load when modified, truncated or generated for another robot; :func:`generate_or_load` reuses a
folder that holds exactly the dataset asked for. Any source (:mod:`.cc`, :mod:`.cosserat`)."""
from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..checks import load_torch_file, prefix_errors, read_json_object
from ..robot import RobotSpec
from .cc import SamplerOptions, generate

TENSOR_FILE, META_FILE = "tensors.pt", "meta.json"


def tensors_sha256(tensors: dict[str, Tensor]) -> str:
    """sha256 over the names, dtypes, shapes and raw bytes of the tensors, in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def options_record(options: Any) -> dict:
    """The options dataclass as meta.json stores it (JSON types: tuples become lists)."""
    return json.loads(json.dumps(asdict(options)))


def save_dataset(directory: str | Path, spec: RobotSpec, tensors: dict[str, Tensor], seed: int,
                 options: Any) -> Path:
    """Write ``tensors.pt`` + ``meta.json`` (spec, source, options, seed, sha256) to ``directory``.

    ``options``: the dataclass the tensors were generated with (:class:`SamplerOptions`, or
    :class:`~dacr_learn.data.cosserat.CosseratOptions`); its ``source`` ("cc", "cosserat") is recorded too."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    meta = {"robot": spec.to_dict(), "source": options.source, "options": options_record(options), "seed": int(seed),
            "num_samples": int(next(iter(tensors.values())).shape[0]), "sha256": tensors_sha256(tensors)}
    tmp = directory / (TENSOR_FILE + ".tmp")
    torch.save(tensors, tmp)
    tmp.replace(directory / TENSOR_FILE)                      # atomic: never a half-written file
    (directory / META_FILE).write_text(json.dumps(meta, indent=2))
    return directory


def _read_meta(directory: Path) -> dict:
    """meta.json of a dataset as a dict (ValueError naming the file when it is not a JSON object)."""
    return read_json_object(directory / META_FILE, f"the {META_FILE} of a dataset written by save_dataset")


def _read_tensors(directory: Path) -> dict[str, Tensor]:
    """tensors.pt of a dataset: a dict of named tensors (ValueError naming the file otherwise)."""
    path = directory / TENSOR_FILE
    expected = f"the {TENSOR_FILE} of a dataset written by save_dataset (a dict of named tensors)"
    tensors = load_torch_file(path, expected)
    if not isinstance(tensors, dict):
        raise ValueError(f"{path}: expected {expected}, found a {type(tensors).__name__}")
    bad = {str(k): type(v).__name__ for k, v in tensors.items() if not (isinstance(k, str) and isinstance(v, Tensor))}
    if bad:
        raise ValueError(f"{path}: expected {expected}, found entries that are not named tensors: {bad}")
    return tensors


def load_dataset(directory: str | Path, spec: RobotSpec | None = None) -> tuple[dict[str, Tensor], dict]:
    """Read a dataset written by :func:`save_dataset`; a ValueError naming the directory or file refuses an
    unreadable, truncated or modified one, or one generated for another robot."""
    directory = Path(directory)
    for f in (TENSOR_FILE, META_FILE):
        if not (directory / f).is_file():
            raise ValueError(f"dataset {directory}: missing {f}")
    meta, tensors = _read_meta(directory), _read_tensors(directory)
    digest = tensors_sha256(tensors)
    if digest != meta.get("sha256"):
        raise ValueError(f"dataset {directory}: checksum mismatch (meta.json says {meta.get('sha256')}, "
                         f"the tensors hash to {digest}); the file was modified or truncated")
    if spec is not None and prefix_errors(directory / META_FILE, RobotSpec.from_dict, meta.get("robot")) != spec:
        raise ValueError(f"dataset {directory}: robot spec mismatch: the dataset was generated for "
                         f"{meta['robot']['name']!r} ({meta['robot']}), expected {spec.to_dict()}")
    return tensors, meta


def generate_or_load(directory: str | Path, spec: RobotSpec, n: int, seed: int,
                     options: Any = None,
                     make: Callable[[RobotSpec, int, int, Any], dict[str, Tensor]] | None = None) -> dict[str, Tensor]:
    """Load ``directory`` if it holds exactly this dataset (spec, n, seed, source, options; no ``source``: "cc"),
    else generate it with ``make(spec, n, seed, options)`` (default :func:`generate`, :class:`~.cc.SamplerOptions`)
    and save it."""
    directory, options = Path(directory), SamplerOptions() if options is None else options
    if (directory / META_FILE).is_file():
        meta = _read_meta(directory)
        if ((meta.get("seed"), meta.get("num_samples"), meta.get("source", "cc"), meta.get("options"))
                == (seed, n, options.source, options_record(options))):
            return load_dataset(directory, spec)[0]
    tensors = (make or generate)(spec, n, seed, options)
    save_dataset(directory, spec, tensors, seed, options)
    return tensors
