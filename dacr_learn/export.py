"""Export trained FK / IK checkpoints as inference modules for controllers, and load them back.

    python -m dacr_learn.export --ckpt runs/fk_type1/version_0/checkpoints/last.ckpt --out exports/fk_type1
    python -m dacr_learn.export --ckpt <ik.ckpt> --out <dir> --no-aoti --dtype float64

From an FK checkpoint: ``fk`` (joint vector (..., N) → pose (..., 4, 4)) and ``jacobian``
(joint vector → pose, J_f (..., 6, D), J_q (..., 6, N)); from an IK checkpoint: ``ik``
(pose (..., 4, 4) → joint vector (..., N)). See :mod:`dacr_learn.deploy.inference` for the modules
(normalisation and Clarke layers folded in, SI units). Each is written as

- ``<name>.pt2``: a ``torch.export`` program (portable; runs op by op, or re-compile it), and
- ``<name>.aoti.pt2``: an AOTInductor package (compiled C++, the lowest latency; needs the same
  torch version and a C++ compiler at export time), unless ``--no-aoti``,

plus ``metadata.json`` next to them: robot spec, feature mode, units, dtype, the source
checkpoint's sha256, each file's sha256, the max deviation from the Lightning model measured
at export, and a checksum of the metadata itself. :func:`load` refuses files whose checksums
do not match (modified, truncated or from another export) and, if asked, a different robot,
feature mode or source checkpoint. These checksums detect accidents, not attacks.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .checks import check_tensor, load_torch_file, read_json_object, short_error
from .console import run_cli
from .deploy.inference import InferenceFK, InferenceIK, InferenceJacobian
from .deploy.inference_compositional import InferenceCompositionalFK, InferenceCompositionalJacobian
from .robot import RobotSpec
from .runs import CHECKPOINT, find_checkpoint, load_lightning_checkpoint

FORMAT = "dacr_learn.export/1"
METADATA_FILE = "metadata.json"
MAX_BATCH = 1 << 16
VERIFY_TOLERANCE = 1e-5      # export fails if an exported module deviates more from the Lightning model
UNITS = {"joint_lengths": "m", "twist": "rad", "position": "m", "rotation": "3x3 matrix in pose[..., :3, :3]",
         "jacobian_rows": "tip linear velocity [m] (rows 0-2) and angular velocity [rad] (rows 3-5), base frame",
         "clarke_features": "rho_re, rho_im [m] per segment, beta [m] and alpha [rad] where actuated"}
_DTYPES = {"float32": torch.float32, "float64": torch.float64}


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
    from .data import generate

    data = generate(spec, n, seed=12345, dtype=torch.float64)
    return {"q": data["q"].to(dtype), "pose": data["pose"].to(dtype)}


def export_program(module: nn.Module, example: Tensor | tuple[Tensor, ...]) -> torch.export.ExportedProgram:
    """torch.export a module with one batched input (or a tuple of inputs sharing the batch dim);
    the batch dim is dynamic (1 … MAX_BATCH)."""
    batch = torch.export.Dim("batch", min=1, max=MAX_BATCH)
    examples = example if isinstance(example, tuple) else (example,)
    with torch.no_grad():
        return torch.export.export(module, examples, dynamic_shapes=tuple({0: batch} for _ in examples))


# Inductor options of ``autotune=True``: small matrix products as generated C++ GEMM kernels (chosen by
# timing them at export) instead of BLAS calls. Measured at batch 1, one thread (docs/export.md): AOTI
# runner of the default synthetic FK 19.0 → 7.7 µs, of FTDCR v4's hardware FK 48 → 27 µs; export slower.
# The last two keep Inductor from writing its timing table of every tuned product to stderr.
AUTOTUNE_CONFIGS = {"max_autotune": True, "max_autotune_gemm_backends": "CPP,ATEN",
                    "autotune_num_choices_displayed": 0, "max_autotune_report_choices_stats": False}


def write_module(name: str, module: nn.Module, example: Tensor | tuple[Tensor, ...], out: Path,
                 aoti: bool, autotune: bool = False) -> dict[str, str]:
    """Write ``<name>.pt2`` and, if asked and it builds (C++ compiler), ``<name>.aoti.pt2`` (with
    :data:`AUTOTUNE_CONFIGS` when ``autotune``, and the module's ``inductor_configs`` if it has them)."""
    program = export_program(module, example)
    files = {"export": f"{name}.pt2"}
    torch.export.save(program, out / files["export"])
    if aoti:
        configs = {**(AUTOTUNE_CONFIGS if autotune else {}), **getattr(module, "inductor_configs", {})} or None
        try:
            torch._inductor.aoti_compile_and_package(program, package_path=str(out / f"{name}.aoti.pt2"),
                                                     inductor_configs=configs)
            files["aoti"] = f"{name}.aoti.pt2"
        except Exception as err:  # no compiler, unsupported platform, …: keep the program
            warnings.warn(f"export {name}: the AOTInductor package did not build ({short_error(err)}); "
                          f"only {files['export']} is written", stacklevel=2)
    return files


def _deviation(reference, loaded, x: Tensor) -> float:
    """Max abs difference between the reference's outputs and a loaded module's (first outputs)."""
    with torch.no_grad():
        ref, got = reference(x), loaded(x)
    ref, got = (ref,) if isinstance(ref, Tensor) else ref, (got,) if isinstance(got, Tensor) else got
    return max((r.double() - g.double()).abs().max().item() for r, g in zip(ref, got, strict=True))


EXPORTERS_GROUP = "dacr_learn.exporters"


@dataclass(frozen=True)
class Exporter:
    """How :func:`export_checkpoint` exports a checkpoint format other than train.py's.

    ``accepts(blob)``: whether the loaded file (``torch.load(..., weights_only=True)``) is of this format;
    ``export(ckpt, out, blob, *, dtype, aoti, autotune)``: write the export to ``out`` and return its
    metadata, like :func:`export_checkpoint`. A package adds its exporter with :func:`register_exporter`,
    and names it under the entry-point group :data:`EXPORTERS_GROUP` so that it is found without this
    module importing that package (dacr_learn's hardware exporter: ``pyproject.toml``)."""

    name: str
    accepts: Callable[[Any], bool]
    export: Callable[..., dict[str, Any]]


_EXPORTERS: dict[str, Exporter] = {}


def register_exporter(exporter: Exporter) -> Exporter:
    """Add ``exporter`` to those :func:`export_checkpoint` tries (a later one of the same name replaces it)."""
    _EXPORTERS[exporter.name] = exporter
    return exporter


def exporters() -> list[Exporter]:
    """The registered exporters, after loading those named under :data:`EXPORTERS_GROUP` (an entry point
    names an :class:`Exporter` object; loading its module registers it)."""
    for entry in entry_points(group=EXPORTERS_GROUP):
        if entry.name not in _EXPORTERS:
            found = entry.load()
            if not isinstance(found, Exporter):
                raise TypeError(f"entry point {entry.value!r} ({EXPORTERS_GROUP}): expected an Exporter, "
                                f"got {type(found).__name__}")
            register_exporter(found)
    return list(_EXPORTERS.values())


def export_checkpoint(ckpt: str | Path, out: str | Path, *, dtype: torch.dtype = torch.float32,
                      aoti: bool | tuple[str, ...] = True, autotune: bool = False) -> dict[str, Any]:
    """Export a checkpoint's inference modules to ``out`` (see the module docstring); returns the metadata.

    ``aoti``: build AOTInductor packages for every module (True), none (False) or the named ones.
    ``autotune``: build them with :data:`AUTOTUNE_CONFIGS` (faster packages, slower export).

    The exported files are loaded back and compared with the Lightning model on 256 samples;
    deviations are recorded (``max_abs_deviation``) and above VERIFY_TOLERANCE the export fails.
    """
    ckpt, out = Path(ckpt), Path(out)
    blob = load_torch_file(ckpt, CHECKPOINT)                  # loaded once: sniffed here, reused below
    for exporter in exporters():                              # another format (e.g. a saved hardware model)
        if exporter.accepts(blob):
            return exporter.export(ckpt, out, blob, dtype=dtype, aoti=aoti, autotune=autotune)
    task, lit = load_lightning_checkpoint(ckpt, blob)
    lit = lit.to(dtype)
    out.mkdir(parents=True, exist_ok=True)
    spec, examples = lit.spec, _examples(lit.spec, 256, dtype)
    sig = signatures(spec)
    meta: dict[str, Any] = {
        "format": FORMAT, "task": task, "robot": spec.to_dict(), "features": lit.hparams.features,
        "rotation": lit.hparams.get("rotation"), "structure": getattr(lit.model, "structure", "monolithic"),
        "dtype": str(dtype).removeprefix("torch."),
        "units": UNITS, "torch_version": torch.__version__, "max_batch": MAX_BATCH, "aoti_autotune": bool(autotune),
        "source_checkpoint": {"path": str(ckpt), "sha256": file_sha256(ckpt)}, "modules": {}}
    for name, module in inference_modules(task, lit.model, dtype).items():
        example = examples[sig[name]["inputs"][0][0]]
        files = write_module(name, module, example[:2], out, aoti if isinstance(aoti, bool) else name in aoti,
                              autotune)
        meta["modules"][name] = {**sig[name], "files": {k: {"file": f, "sha256": file_sha256(out / f)}
                                                        for k, f in files.items()}}
    meta["metadata_sha256"] = metadata_digest(meta)
    (out / METADATA_FILE).write_text(json.dumps(meta, indent=2))
    _verify(out, meta, lit.model, examples)
    return meta


def _verify(out: Path, meta: dict, model: nn.Module, examples: dict[str, Tensor]) -> None:
    """Load every exported file, record its max deviation from ``model`` and fail above tolerance."""
    worst = {}
    for name, info in meta["modules"].items():
        x = examples[info["inputs"][0][0]]
        for entry in info["files"].values():
            loaded = load(out / entry["file"])
            first = loaded if name != "jacobian" else (lambda q, m=loaded: m(q)[0])
            worst[entry["file"]] = _deviation(model, first, x)
    meta["max_abs_deviation"] = worst
    meta["metadata_sha256"] = metadata_digest(meta)
    (out / METADATA_FILE).write_text(json.dumps(meta, indent=2))
    bad = {f: e for f, e in worst.items() if not e <= VERIFY_TOLERANCE}
    if bad:
        raise RuntimeError(f"export {out}: modules deviate from the Lightning model by more than "
                           f"{VERIFY_TOLERANCE}: {bad}")


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
        self.dtype = _DTYPES[metadata["dtype"]]

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


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """CLI: export a checkpoint; prints the written files and the verified deviations."""
    p = argparse.ArgumentParser(prog="python -m dacr_learn.export", description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", required=True,
                   help="FKModule / IKModule checkpoint, or a train.py run folder (runs/<name>: its newest "
                        "version's last.ckpt; runs/<name>/version_<n>), or a hardware model.pt")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--dtype", choices=sorted(_DTYPES), default="float32")
    p.add_argument("--no-aoti", action="store_true", help="skip the AOTInductor packages (faster export)")
    p.add_argument("--autotune", action="store_true",
                   help="build the AOTInductor packages with generated C++ GEMM kernels chosen by timing "
                        "(faster at batch 1, slower export)")
    args = p.parse_args(argv)
    if args.autotune and args.no_aoti:
        p.error("--autotune tunes the AOTInductor packages; it cannot be combined with --no-aoti")
    args.ckpt = str(find_checkpoint(args.ckpt))
    meta = export_checkpoint(args.ckpt, args.out, dtype=_DTYPES[args.dtype], aoti=not args.no_aoti,
                             autotune=args.autotune)
    print(f"exported {meta['task'].upper()} of robot {meta['robot']['name']!r} ({meta['features']} features, "
          f"{meta['dtype']}) from {args.ckpt} to {args.out}/")
    source = "Lightning" if meta["task"] in ("fk", "ik") else "saved model"   # hardware: the loaded checkpoint
    for f, dev in meta["max_abs_deviation"].items():
        print(f"  {f:<22} max |exported − {source}| = {dev:.2e}")
    print(f"  load with: dacr_learn.export.load('{args.out}', '{next(iter(meta['modules']))}')")
    return meta


if __name__ == "__main__":
    # run the package's own module, not this __main__ copy of it: exporters register into
    # dacr_learn.export's registry and are instances of its Exporter class
    from dacr_learn.export import main as package_main

    sys.exit(run_cli(package_main))       # a bad --ckpt: its one-line message, not a traceback
