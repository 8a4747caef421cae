"""Exported inference modules: writing, verifying and loading them, for every model family; and the exporter
of ``train.py`` checkpoints (FK / IK). The command line and the dispatch on a checkpoint's format are in
:mod:`dacr_learn.export` (``python -m dacr_learn.export``); the exporter of saved hardware models in
:mod:`dacr_learn.hardware.deploy.export`.

An export is a folder of ``<name>.pt2`` programs, ``<name>.aoti.pt2`` packages and ``metadata.json`` (its
contents: docs/export.md, "Export"); :func:`write_export` measures each loaded file's deviation from its model (the
export fails above :data:`VERIFY_TOLERANCE`); :func:`load` refuses files whose checksums do not match (accidents,
not attacks).

From a ``train.py`` checkpoint (:func:`export_trained`, rebuilt without Lightning by
:func:`dacr_learn.runs.load_checkpoint_model`): FK gives ``fk`` (joint vector (..., N) → pose (..., 4, 4)) and
``jacobian`` (→ pose, J_f (..., 6, D), J_q (..., 6, N)); IK gives ``ik`` (pose (..., 4, 4) → joint vector (..., N)).
The modules: :mod:`dacr_learn.deploy.inference` (SI units).
"""
from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..checks import check_tensor, load_torch_file, read_json_object, short_error
from ..robot import RobotSpec
from ..runs import CHECKPOINT, load_checkpoint_model
from .inference import InferenceFK, InferenceIK, InferenceJacobian
from .inference_compositional import InferenceCompositionalFK, InferenceCompositionalJacobian
from .package_metadata import package_metadata

FORMAT = "dacr_learn.export/1"
METADATA_FILE = "metadata.json"
MAX_BATCH = 1 << 16
VERIFY_TOLERANCE = 1e-5      # export fails if an exported module deviates more from the model it was made from
UNITS = {"joint_lengths": "m", "twist": "rad", "position": "m", "rotation": "3x3 matrix in pose[..., :3, :3]",
         "jacobian_rows": "tip linear velocity [m] (rows 0-2) and angular velocity [rad] (rows 3-5), base frame",
         "clarke_features": "rho_re, rho_im [m] per segment, beta [m] and alpha [rad] where actuated"}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def metadata_digest(meta: dict) -> str:
    body = {k: v for k, v in meta.items() if k != "metadata_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def export_program(module: nn.Module, example: Tensor | tuple[Tensor, ...]) -> torch.export.ExportedProgram:
    """torch.export a module with one batched input (or a tuple of inputs sharing the batch dim);
    the batch dim is dynamic (1 … MAX_BATCH). The examples are made contiguous first: a compiled package assumes
    its example's strides, and its callers (C++, the package's runner) pass contiguous tensors."""
    batch = torch.export.Dim("batch", min=1, max=MAX_BATCH)
    examples = tuple(x.contiguous() for x in (example if isinstance(example, tuple) else (example,)))
    with torch.no_grad():
        return torch.export.export(module, examples, dynamic_shapes=tuple({0: batch} for _ in examples))


def _products(a: Tensor, b: Tensor) -> Tensor:
    """a @ b as a sum of broadcast products (matmul's broadcasting; 1-D operands too): a loop the compiler writes
    inline."""
    if a.dim() == 1:
        return (a.unsqueeze(-1) * b).sum(-2) if b.dim() > 1 else (a * b).sum(-1)
    if b.dim() == 1:
        return (a * b).sum(-1)
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def _scaled_sum(c: Tensor, a: Tensor, b: Tensor, beta=1, alpha=1) -> Tensor:
    return beta * c + alpha * _products(a, b)


SMALL_MATMULS = {op: _products for op in (torch.ops.aten.matmul.default, torch.ops.aten.mm.default,
                                          torch.ops.aten.bmm.default)} | {
    op: _scaled_sum for op in (torch.ops.aten.addmm.default, torch.ops.aten.baddbmm.default)}
"""Decompositions of small matrix products: an external BLAS call in a compiled module keeps its temporaries off
the stack and wraps each operand in a heap-allocated tensor handle (tens of µs per call at batch 1)."""


def inline_products(program: torch.export.ExportedProgram) -> torch.export.ExportedProgram:
    """``program`` with its matrix products written as inline sums (:data:`SMALL_MATMULS`), for AOTInductor
    packages of small products (a module asks for it with ``inline_products = True``, :func:`write_module`)."""
    table = torch.export.default_decompositions()
    table.update(SMALL_MATMULS)
    return program.run_decompositions(table)


# Inductor options of ``autotune=True``: small matrix products as generated C++ GEMM kernels (chosen by
# timing them at export) instead of BLAS calls. Measured at batch 1, one thread (docs/export.md): AOTI
# runner of the default synthetic FK 19.0 → 7.7 µs, of FTDCR v4's hardware FK 48 → 27 µs; export slower.
# The last two keep Inductor from writing its timing table of every tuned product to stderr.
AUTOTUNE_CONFIGS = {"max_autotune": True, "max_autotune_gemm_backends": "CPP,ATEN",
                    "autotune_num_choices_displayed": 0, "max_autotune_report_choices_stats": False}


# Inductor options of every AOTI package: intermediate buffers carved out of one pool instead of one allocation
# each per call (bit-identical outputs; at batch 1 the allocations cost more than the Jacobians' arithmetic: AOTI
# compositional Jacobian 53.9 → 39.2 µs, docs/history/export.md).
PACKAGE_CONFIGS = {"memory_planning": True}


def write_module(name: str, module: nn.Module, example: Tensor | tuple[Tensor, ...], out: Path,
                 aoti: bool, autotune: bool = False, metadata: dict[str, str] | None = None) -> dict[str, str]:
    """Write ``<name>.pt2`` and, if asked and it builds (C++ compiler), ``<name>.aoti.pt2`` (with
    :data:`PACKAGE_CONFIGS`, :data:`AUTOTUNE_CONFIGS` when ``autotune``, and the module's ``inductor_configs`` if
    it has them; its matrix products inline, :func:`inline_products`, if it has ``inline_products = True``).
    ``metadata``: strings stored inside the package (:mod:`.package_metadata`, read by C++ loaders)."""
    program = export_program(module, example)
    files = {"export": f"{name}.pt2"}
    torch.export.save(program, out / files["export"])
    if aoti:
        configs = {**PACKAGE_CONFIGS, **(AUTOTUNE_CONFIGS if autotune else {}),
                   **getattr(module, "inductor_configs", {}), "aot_inductor.metadata": dict(metadata or {})}
        try:
            compiled = inline_products(program) if getattr(module, "inline_products", False) else program
            torch._inductor.aoti_compile_and_package(compiled, package_path=str(out / f"{name}.aoti.pt2"),
                                                     inductor_configs=configs)
            files["aoti"] = f"{name}.aoti.pt2"
        except Exception as err:  # no compiler, unsupported platform, …: keep the program
            warnings.warn(f"export {name}: the AOTInductor package did not build ({short_error(err)}); "
                          f"only {files['export']} is written", stacklevel=2)
    return files


def output_folder(out: str | Path) -> Path:
    """The export folder ``out``, created with its parents; ValueError naming it when something is in the way
    (``out`` or one of its parents is a file) or it cannot be made."""
    out = Path(out)
    blocked = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocked is not None:
        where = "is a file" if blocked == out else f"has a file in its path ({blocked})"
        raise ValueError(f"--out {out}: {where}; expected a folder for the exported modules (created if missing)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {out}: cannot create the folder ({err.strerror or err})") from err
    return out


def export_header(ckpt: Path, task: str, dtype: torch.dtype, autotune: bool) -> dict[str, Any]:
    """The metadata entries every export has (task-specific ones are added by its exporter)."""
    return {"format": FORMAT, "task": task, "dtype": str(dtype).removeprefix("torch."),
            "torch_version": torch.__version__, "max_batch": MAX_BATCH, "aoti_autotune": bool(autotune),
            "source_checkpoint": {"path": str(ckpt), "sha256": file_sha256(ckpt)}, "modules": {}}


def write_export(out: Path, meta: dict[str, Any], modules: dict[str, nn.Module],
                 inputs: dict[str, tuple[Tensor, ...]], references: dict[str, Callable], *,
                 aoti: bool | tuple[str, ...], autotune: bool, against: str) -> dict[str, Any]:
    """Write ``modules`` (name → module, exported with the first two rows of ``inputs[name]`` as examples) into
    ``out``, load every written file back, compare it on ``inputs[name]`` with ``references[name]`` (its outputs
    against the first outputs of the loaded module) and write ``metadata.json`` (``meta`` with each module's
    signature under ``meta["modules"][name]``, completed with the files, their checksums and the deviations).
    ``aoti``: AOTInductor packages for every module (True), none (False) or the named ones. RuntimeError naming
    ``against`` (what the references are) when a deviation exceeds :data:`VERIFY_TOLERANCE`."""
    for name, module in modules.items():
        files = write_module(name, module, tuple(x[:2] for x in inputs[name]), out,
                             aoti if isinstance(aoti, bool) else name in aoti, autotune, package_metadata(meta, name))
        meta["modules"][name]["files"] = {k: {"file": f, "sha256": file_sha256(out / f)} for k, f in files.items()}
    worst = {}
    for name, info in meta["modules"].items():
        for kind, entry in info["files"].items():
            loaded = ExportedModule(module_runner(out / entry["file"], kind, meta), meta, name, kind)
            worst[entry["file"]] = _deviation(references[name], loaded, inputs[name])
    meta["max_abs_deviation"] = worst
    meta["metadata_sha256"] = metadata_digest(meta)
    (out / METADATA_FILE).write_text(json.dumps(meta, indent=2))
    bad = {f: e for f, e in worst.items() if not e <= VERIFY_TOLERANCE}
    if bad:
        raise RuntimeError(f"export {out}: modules deviate from {against} by more than {VERIFY_TOLERANCE}: {bad}")
    return meta


def _deviation(reference: Callable, loaded: nn.Module, inputs: tuple[Tensor, ...]) -> float:
    """Max abs difference between the reference's outputs and the first outputs of a loaded module."""
    with torch.no_grad():
        ref, got = reference(*inputs), loaded(*inputs)
    ref, got = (ref,) if isinstance(ref, Tensor) else ref, (got,) if isinstance(got, Tensor) else got
    return max((r.double() - g.double()).abs().max().item() for r, g in zip(ref, got, strict=False))


def inference_modules(task: str, model: nn.Module, dtype: torch.dtype = torch.float32) -> dict[str, nn.Module]:
    """The plain nn.Modules of a trained models.FKModel ("fk") or models.IKModel ("ik"), in eval mode.
    A compositional FK model (compositional.CompositionalFK) gives ``fk``, and ``jacobian`` with the twist head."""
    if task == "fk" and getattr(model, "structure", "monolithic") == "compositional":
        modules = {"fk": InferenceCompositionalFK(model, dtype).eval()}
        if model.rotation == "twist":
            modules["jacobian"] = InferenceCompositionalJacobian(model, dtype).eval()
        return modules
    if task == "fk":
        return {"fk": InferenceFK(model, dtype).eval(), "jacobian": InferenceJacobian(model, dtype).eval()}
    if task == "ik":
        return {"ik": InferenceIK(model, dtype).eval()}
    raise ValueError(f"task: expected 'fk' or 'ik', got {task!r}")


def signatures(spec: RobotSpec) -> dict[str, dict[str, list]]:
    """Trailing shapes of each module's input and outputs (every tensor has leading batch dims)."""
    n, d = spec.num_joints, spec.num_actuated_features
    return {"fk": {"inputs": [["q", [n]]], "outputs": [["pose", [4, 4]]]},
            "jacobian": {"inputs": [["q", [n]]], "outputs": [["pose", [4, 4]], ["J_f", [6, d]], ["J_q", [6, n]]]},
            "ik": {"inputs": [["pose", [4, 4]]], "outputs": [["q", [n]]]}}


def _examples(spec: RobotSpec, n: int, dtype: torch.dtype) -> dict[str, Tensor]:
    from ..data import generate

    data = generate(spec, n, seed=12345, dtype=torch.float64)
    return {"q": data["q"].to(dtype), "pose": data["pose"].to(dtype)}


def read_metadata(directory: str | Path) -> dict[str, Any]:
    """Read and check ``metadata.json`` of an export directory (format and self-checksum)."""
    path = Path(directory) / METADATA_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no export metadata next to the module; export with "
                                f"`python -m dacr_learn.export --ckpt <ckpt> --out {directory}`")
    meta = read_json_object(path, f"the {METADATA_FILE} of an export")
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: format {meta.get('format')!r} is not {FORMAT!r}; re-export the checkpoint")
    if meta.get("metadata_sha256") != metadata_digest(meta):
        raise ValueError(f"{path}: checksum mismatch: the metadata was modified after export")
    return meta


def _find_module(meta: dict, file_name: str) -> tuple[str, str, str]:
    for name, info in meta["modules"].items():
        for kind, entry in info["files"].items():
            if entry["file"] == file_name:
                return name, kind, entry["sha256"]
    raise ValueError(f"{file_name}: not a file of this export (metadata lists "
                     f"{[e['file'] for i in meta['modules'].values() for e in i['files'].values()]})")


def _check_expectations(meta: dict, path: Path, robot, features, checkpoint) -> None:
    if robot is not None:
        want = RobotSpec.coerce(robot)
        if RobotSpec.from_dict(meta["robot"]) != want:
            raise ValueError(f"{path}: robot spec mismatch: exported for {meta['robot']['name']!r} "
                             f"({meta['robot']}), expected {want.to_dict()}")
    if features is not None and meta["features"] != features:
        raise ValueError(f"{path}: feature mode mismatch: exported with {meta['features']!r}, expected {features!r}")
    if checkpoint is not None:
        digest = file_sha256(checkpoint)
        if digest != meta["source_checkpoint"]["sha256"]:
            raise ValueError(f"{path}: exported from a different checkpoint ({meta['source_checkpoint']['path']}, "
                             f"sha256 {meta['source_checkpoint']['sha256'][:12]}…), not {checkpoint} "
                             f"(sha256 {digest[:12]}…)")


def module_runner(path: Path, kind: str, meta: dict):
    """A callable list[Tensor] → list[Tensor] for an AOTInductor package or a torch.export program."""
    if kind == "aoti":
        if meta["torch_version"] != torch.__version__:
            raise ValueError(f"{path}: AOTInductor package built with torch {meta['torch_version']}, "
                             f"this is torch {torch.__version__}; load the .pt2 program or re-export")
        compiled = torch._inductor.aoti_load_package(str(path))
        loader = getattr(compiled, "loader", None)
        return loader.run if loader is not None else (lambda xs: list(compiled(*xs)))
    module = torch.export.load(path).module()

    def run(xs: list[Tensor]) -> list[Tensor]:
        out = module(*xs)
        return [out] if isinstance(out, Tensor) else list(out)
    return run


def load(path: str | Path, name: str | None = None, *, robot=None, features: str | None = None,
         checkpoint: str | Path | None = None) -> ExportedModule:
    """Load an exported module as a callable nn.Module (no Lightning needed).

    Args:
        path: an exported file (``fk.pt2``, ``fk.aoti.pt2``, …) or an export directory with ``name``
            ("fk" | "jacobian" | "ik"), which picks the AOTInductor package when there is one.
        robot, features, checkpoint: optional expectations (RobotSpec / dict / YAML path, feature
            mode, source checkpoint path); a mismatch is a ValueError.
    Raises FileNotFoundError without ``metadata.json``; ValueError for a modified file or metadata.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such export folder or exported file; export a checkpoint with "
                                f"`python -m dacr_learn.export --ckpt <ckpt> --out {path}`")
    if path.is_dir():
        meta = read_metadata(path)
        if name not in meta["modules"]:
            raise ValueError(f"name: expected one of {sorted(meta['modules'])} for {path}, got {name!r}")
        files = meta["modules"][name]["files"]
        aoti = "aoti" in files and meta["torch_version"] == torch.__version__
        path = path / files["aoti" if aoti else "export"]["file"]
    meta = read_metadata(path.parent)
    name, kind, digest = _find_module(meta, path.name)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: listed in {METADATA_FILE} but missing")
    actual = file_sha256(path)
    if actual != digest:
        raise ValueError(f"{path}: checksum mismatch (sha256 {actual[:12]}…, {METADATA_FILE} records {digest[:12]}…): "
                         "the file was modified, truncated or comes from another export")
    _check_expectations(meta, path, robot, features, checkpoint)
    return ExportedModule(module_runner(path, kind, meta), meta, name, kind)


class ExportedModule(nn.Module):
    """A loaded export (synthetic FK / Jacobian / IK, or a hardware model's modules): checks every
    input (shape (..., *shape), floating dtype, finite values, non-empty), accepts leading batch dims
    shared by all inputs and float32/float64 (computed in the export's dtype, returned in the first
    input's). Returns one tensor, or a tuple when the module has several outputs (``jacobian``:
    pose, J_f, J_q; hardware ``fk``: tip, tip_std[, state]).

    Attributes: ``metadata`` (dict of metadata.json), ``name``, ``kind`` ("aoti" | "export"),
    ``inputs`` ([(name, shape)] of the module's inputs).
    """

    def __init__(self, runner, metadata: dict, name: str, kind: str):
        super().__init__()
        self.runner, self.metadata, self.name, self.kind = runner, metadata, name, kind
        info = metadata["modules"][name]
        self.inputs = [(n, tuple(s)) for n, s in info["inputs"]]
        self._labels = [f"{name} input {n}" for n, _ in self.inputs]   # error prefixes, built once
        self.output_shapes = [tuple(s) for _, s in info["outputs"]]
        self.dtype = DTYPES[metadata["dtype"]]

    def extra_repr(self) -> str:
        return f"name={self.name!r}, kind={self.kind!r}, robot={self.metadata['robot']['name']!r}"

    def forward(self, *xs: Tensor):
        if len(xs) != len(self.inputs):
            raise ValueError(f"{self.name}: expected inputs {[n for n, _ in self.inputs]}, got {len(xs)} tensors")
        lead, fast = None, True
        for x, (_, shape), label in zip(xs, self.inputs, self._labels, strict=True):
            check_tensor(x, label, shape, nonempty=True)
            here = x.shape[:x.dim() - len(shape)]
            if lead is not None and here != lead:
                raise ValueError(f"{self.name}: inputs must share their batch dims, got {tuple(lead)} and "
                                 f"{tuple(here)}")
            lead, fast = here, fast and x.dtype == self.dtype and x.is_contiguous()
        if fast and len(lead) == 1:                                   # fast path: (B, ...) as exported
            outs = self.runner(list(xs))
        else:
            outs = self.runner([x.reshape(-1, *s).to(self.dtype).contiguous()
                                for x, (_, s) in zip(xs, self.inputs, strict=True)])
            outs = [o.reshape(*lead, *s).to(xs[0].dtype) for o, s in zip(outs, self.output_shapes, strict=True)]
        return outs[0] if len(outs) == 1 else tuple(outs)


# The exporter of train.py checkpoints
def export_trained(ckpt: str | Path, out: str | Path, blob: Any = None, *, dtype: torch.dtype = torch.float32,
                   aoti: bool | tuple[str, ...] = True, autotune: bool = False) -> dict[str, Any]:
    """Export an FK / IK checkpoint's inference modules to ``out`` (module docstring); returns the metadata.

    ``blob``: the file's content when the caller has loaded it (not loaded again). The exported files are
    loaded back and compared with the checkpoint's model on 256 samples (:func:`write_export`).
    """
    ckpt = Path(ckpt)
    blob = load_torch_file(ckpt, CHECKPOINT) if blob is None else blob
    task, model = load_checkpoint_model(ckpt, blob)
    model, hparams = model.to(dtype), blob["hyper_parameters"]
    out, spec = output_folder(out), model.spec
    examples, sig = _examples(spec, 256, dtype), signatures(spec)
    meta = {**export_header(ckpt, task, dtype, autotune), "robot": spec.to_dict(), "features": hparams["features"],
            "rotation": hparams.get("rotation"), "structure": getattr(model, "structure", "monolithic"),
            "units": UNITS}
    modules = inference_modules(task, model, dtype)
    meta["modules"] = {name: dict(sig[name]) for name in modules}
    inputs = {name: (examples[sig[name]["inputs"][0][0]],) for name in modules}
    return write_export(out, meta, modules, inputs, dict.fromkeys(modules, model), aoti=aoti, autotune=autotune,
                        against="the checkpoint's model")
