"""Input validation: tensors given to the public functions, and the files a user hands in.

Every failure is a ValueError naming the tensor or file, what was expected and what was found
(a missing file stays a FileNotFoundError naming its path); the original error is chained.
"""
from __future__ import annotations

import itertools
import json
import math
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

F64 = torch.float64   # the dtype of the IK solver, the controllers and every float64 exported module


def to_f64(x: Tensor) -> Tensor:
    """``x`` in float64: ``x`` itself when it already is (no dispatch: it sits in control loops)."""
    return x if x.dtype == F64 else x.to(F64)


_PY_SUM_MAX = 256   # elements up to which check_tensor's finiteness sum runs in Python (see there)


def _sum_is_finite(x: Tensor) -> bool:
    """Whether the sum of all entries of x is finite (False for any NaN/inf entry, or an overflow).
    Small tensors: the nested list of ``tolist`` flattened in Python, no tensor (view) created — a view's
    allocation alone slowed the AOTI call after it by a few µs (docs/export.md)."""
    if x.numel() <= _PY_SUM_MAX:
        values = x.tolist()
        if x.dim() == 0:
            return math.isfinite(values)
        for _ in range(x.dim() - 1):
            values = itertools.chain.from_iterable(values)
        return math.isfinite(sum(values))
    return math.isfinite(x.sum().item())


def as_floating(x: Any, name: str, what: str = "values") -> Tensor:
    """``x`` as a tensor (torch.as_tensor of a list or array); ValueError naming ``name`` unless floating point."""
    x = x if isinstance(x, Tensor) else torch.as_tensor(x)
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected floating-point {what}, got dtype {x.dtype}")
    return x


def check_tensor(x: Tensor, name: str, trailing: tuple[int, ...], finite: bool = True, nonempty: bool = False) -> None:
    """Raise ValueError unless ``x`` is a floating tensor of shape (..., *trailing) with finite values
    (and, with ``nonempty``, at least one element).

    Skipped while tracing for torch.export / torch.compile (the checks are data dependent); under
    torch.func transforms (vmap, jacfwd, jacrev) only the shape and dtype are checked. The
    accepting path is a few attribute reads and one sum (it sits in every exported call); the error
    messages are built only on failure (:func:`_raise_bad_tensor`).
    """
    if torch.compiler.is_compiling():
        return
    # A NaN/inf anywhere makes the sum non-finite, so one sum decides (the exact elementwise test runs
    # only when it fails: a NaN/inf, or a huge finite sum that overflowed). For the few values of a
    # controller's batch the sum is taken in Python over x.tolist(): no tensor op whose allocation
    # slows the AOTI call after it. Above _PY_SUM_MAX elements it is one torch reduction read back.
    trailing = tuple(trailing)
    k = len(trailing)
    if finite and isinstance(x, Tensor) and torch._C._functorch.is_functorch_wrapped_tensor(x):
        finite = False     # under torch.func (vmap, jacfwd) the values are not readable: shapes only
    if (isinstance(x, Tensor) and x.is_floating_point() and x.dim() >= k and x.shape[x.dim() - k:] == trailing
            and (not nonempty or x.numel() > 0)
            and (not finite or _sum_is_finite(x) or bool(torch.isfinite(x).all()))):
        return
    _raise_bad_tensor(x, name, trailing, nonempty)


def _raise_bad_tensor(x, name: str, trailing: tuple[int, ...], nonempty: bool) -> None:
    """The ValueError of :func:`check_tensor` for an ``x`` it rejected: what was expected, what was found."""
    k, expected = len(trailing), f"(..., {', '.join(map(str, trailing))})"
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape {expected}, got {type(x).__name__}")
    if x.dim() < k or tuple(x.shape[x.dim() - k:]) != trailing:
        raise ValueError(f"{name}: expected shape {expected}, got a tensor of shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    if nonempty and x.numel() == 0:
        raise ValueError(f"{name}: expected a non-empty batch, got shape {tuple(x.shape)}")
    bad = (~torch.isfinite(x)).sum().item()
    raise ValueError(f"{name}: expected finite values of shape {expected}, got {bad} NaN/inf entries "
                     f"in a tensor of shape {tuple(x.shape)}")


def check_choice(name: str, value: Any, choices: tuple | dict) -> None:
    """ValueError ``"<name>: expected one of <choices>, got <value!r>"`` unless ``value`` is one of ``choices``
    (a dict's keys, listed sorted)."""
    if value not in choices:
        shown = sorted(choices) if isinstance(choices, dict) else choices
        raise ValueError(f"{name}: expected one of {shown}, got {value!r}")


def short_error(err: BaseException) -> str:
    """One line of an exception: its type and the first 160 characters of its message."""
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text[:160]}{'…' if len(text) > 160 else ''}" if text else type(err).__name__


def prefix_errors(where: Any, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``; a ValueError it raises is raised again as ``"<where>: <message>"`` (chained), so that the
    message of a check names the file or the flag the checked value came from."""
    try:
        return fn(*args)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from err


def existing(path: str | Path, expected: str) -> Path:
    """``path`` as a Path; FileNotFoundError ``"<path>: no such file; expected <expected>"`` when it does not exist."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file; expected {expected}")
    return path


def read_text(path: str | Path, expected: str) -> str:
    """The text of a user's file; ValueError ``"<path>: expected <expected>, found …"`` when it is
    a directory, unreadable or not UTF-8. A missing file raises FileNotFoundError naming the path."""
    path = existing(path, expected)
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: expected {expected}, found a file that cannot be read as UTF-8 text "
                         f"({short_error(err)})") from err


def read_yaml(path: str | Path, expected: str) -> Any:
    """The parsed content of a user's YAML file (ValueError naming the file and the line of a syntax error)."""
    import yaml

    text = read_text(path, expected)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        found = f"{getattr(err, 'problem', None) or short_error(err)}{where}"
        raise ValueError(f"{path}: expected {expected}, found invalid YAML ({found})") from err


def read_json_object(path: str | Path, expected: str) -> dict[str, Any]:
    """The JSON object (dict) in a user's file; ValueError naming the file for invalid JSON or another type."""
    text = read_text(path, expected)
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: expected {expected}, found invalid JSON ({short_error(err)})") from err
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected {expected} (a JSON object), found a JSON {type(obj).__name__}")
    return obj


def load_torch_file(path: str | Path, expected: str) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU of a user's file; ValueError naming the file
    when it is not a (complete) torch.save archive. A missing file raises FileNotFoundError."""
    path = existing(path, expected)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # torch.load raises RuntimeError, OSError, EOFError, UnpicklingError, …
        if path.is_file() and not zipfile.is_zipfile(path):      # torch.save writes a zip archive
            found = (f"a file of {path.stat().st_size} bytes that is not a complete torch.save archive "
                     "(truncated, or not a torch file)")
        else:
            found = f"a file that torch.load cannot read ({short_error(err)})"
        raise ValueError(f"{path}: expected {expected}, found {found}") from err
