"""Save and load a fitted hardware tip model: calibration, servo map, CC parameters, ensemble members.

A checkpoint is one ``torch.save`` file of plain dicts, lists, numbers, strings and tensors, loadable with
``torch.load(path, weights_only=True)``::

    format: "dacr_learn.hardware_model/3" (CC Clarke-residual family, :class:`~.learned.CCClarkeResidual`
        and :class:`~.learned.CCClarkeResidualHistory`) or "/2" (compositional members,
        :class:`~.compositional_model.CCCompositionalResidual`: the ``structure`` and ``compositional`` entries)
    model: registry name; history: bool; play_width [m]; robot: the calibrated RobotSpec as a dict;
    servo_map: ServoMap.to_dict(); servo_ids: column order; units: "mm" (servo commands; tips are metres)
    cc: CalibratedCC state dict; members: [each member's state dict without the cc.* keys]
    structure (/2 only): "compositional"; compositional (/2 only): {"context", "width", "depth", "torsion"}
    sigma_calibration: {"scale", "floor" [m]} or None; sigma_model: SigmaModel.to_dict() or None (the σ of
        :meth:`HardwareModel.predict`); support: SupportModel state dict or None
    examples: (n, S) training commands [mm] in time order (to verify exports), or None
    info: free-form dict (command line; ``servo_range_mm``: {"lower", "upper"} [mm], the range of every servo
        command of the training recording: :meth:`HardwareModel.servo_range`)

Format /1 (written until 2026-11-25) is /3 plus the research options ``clamp`` (False) and ``gate_width``
(None) and the member buffers ``rho_max``, ``train_clarke``; it still loads (the buffers dropped), unless
the options are set (ValueError). Older code rejects a format it does not know instead of misreading it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import nn

from ...body import BodyPoints
from ...checks import load_torch_file
from ...folding import linear_layers
from ...robot import RobotSpec
from ...runs import CHECKPOINT, find_checkpoint
from ..ccmodel import CalibratedCC
from ..compositional_model import CCCompositionalResidual
from ..learned import PLAY_WIDTH, CCClarkeResidual, CCClarkeResidualHistory, Split, command_split
from ..servo_map import ServoMap
from .uncertainty import SigmaCalibration, SigmaModel, SupportModel, mean_and_sigma

FORMAT = "dacr_learn.hardware_model/3"                       # the CC Clarke-residual family
FORMAT_COMPOSITIONAL = "dacr_learn.hardware_model/2"         # structure "compositional"
FORMAT_V1 = "dacr_learn.hardware_model/1"                    # /3 + research options (read, not written)
FORMATS = (FORMAT, FORMAT_COMPOSITIONAL, FORMAT_V1)
_V1_BUFFERS = ("rho_max", "train_clarke")                    # member buffers of the /1 research options
_KEYS = ("format", "model", "history", "play_width", "robot", "servo_map", "servo_ids", "units", "cc", "members")


@dataclass
class HardwareModel:
    """A loaded (or freshly fitted) hardware model: everything needed to predict from servo commands."""

    name: str
    spec: RobotSpec
    smap: ServoMap
    servo_ids: tuple[str, ...]
    cc: CalibratedCC
    members: list[CCClarkeResidual] | list[CCCompositionalResidual]
    play_width: float = PLAY_WIDTH
    sigma: SigmaCalibration | None = None
    support: SupportModel | None = None
    examples: torch.Tensor | None = None
    info: dict[str, Any] = field(default_factory=dict)
    sigma_model: SigmaModel | None = None

    @property
    def history(self) -> bool:
        """True when the members use the command history (a play-operator state; compositional members do not)."""
        return bool(getattr(self.members[0], "history", False))

    @property
    def compositional(self) -> bool:
        """True when the members are :class:`~.compositional_model.CCCompositionalResidual` models."""
        return isinstance(self.members[0], CCCompositionalResidual)

    def split(self, servo_mm: torch.Tensor, static: bool = False) -> Split:
        """The model inputs of commands servo (n, S) [mm, ``servo_ids`` order; time order for a history model]
        (:func:`~.learned.command_split`; no measured tips: the split's tip is NaN). ``static``: every command
        on its own, as the start of a sequence (no motion memory: what a held command gives without history)."""
        split = command_split(self._servo_m(servo_mm), self.servo_ids, self.spec, self.smap, self.cc)
        return dataclasses.replace(split, memory=torch.zeros_like(split.memory)) if static else split

    def predict(self, commands: torch.Tensor | Split, static: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(tip (n, 3) [m] = ensemble mean, σ (n, 3) [m], :meth:`sigma_of`) of servo commands (n, S) [mm] or a Split;
        ``static``: each command on its own (:meth:`split`), e.g. the candidates of an IK solve, not a sequence."""
        split = commands if isinstance(commands, Split) else self.split(commands, static)
        with torch.no_grad():
            preds = torch.stack([m(split) for m in self.members])
        return mean_and_sigma(preds, split.cc_tip, split.features[..., :2], self.sigma_of(), self.support)

    def body(self, servo_mm: torch.Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The body of servo commands (n, S) [mm, ``servo_ids`` order]: the calibrated CC model's
        (:meth:`~..ccmodel.CalibratedCC.body`), motion-capture frame, float64; near the tip it can be off the predicted
        tip by the learned residual (which corrects the tip only)."""
        x = self.smap.command_displacements(self.spec, self.servo_ids, self._servo_m(servo_mm))
        with torch.no_grad():
            return self.cc.body(x, points_per_segment)

    def _servo_m(self, servo_mm: torch.Tensor) -> torch.Tensor:
        """Commands (n, S) [mm, ``servo_ids`` order] in metres, float64; ValueError for another shape."""
        servo = 1e-3 * torch.as_tensor(servo_mm, dtype=torch.float64)
        if servo.dim() != 2 or servo.shape[-1] != len(self.servo_ids):
            raise ValueError(f"servo_mm: expected shape (n, {len(self.servo_ids)}) [mm], got {tuple(servo.shape)}")
        return servo

    def sigma_of(self) -> SigmaModel:
        """The σ this model reports: the stored σ model, else the σ calibration (an ``ensemble``-term σ
        model; without one the raw ensemble std)."""
        return self.sigma_model or (self.sigma or SigmaCalibration()).as_model()

    def servo_range(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower, upper) (S,) float64 [mm, ``servo_ids`` order]: the range of the commands recorded in training,
        ``info["servo_range_mm"]`` (the whole recording), else, in files saved before it was stored, the range of
        the ``examples`` (the recording's first rows: a narrower box). ValueError when neither is there."""
        stored = self.info.get("servo_range_mm")
        if stored is not None:
            lower, upper = (torch.as_tensor(stored[k], dtype=torch.float64) for k in ("lower", "upper"))
            if lower.shape != (len(self.servo_ids),) or upper.shape != lower.shape or not bool((upper >= lower).all()):
                raise ValueError(f"info['servo_range_mm']: expected lower ≤ upper, {len(self.servo_ids)} values each "
                                 f"[mm], got {stored}")
            return lower, upper
        if self.examples is None or self.examples.shape[0] < 2:
            raise ValueError("servo_range: this hardware model was saved without its training commands (examples, "
                             "info['servo_range_mm']), so the recorded servo range is unknown; save it again with "
                             "--save")
        commands = self.examples.to(torch.float64)
        return commands.amin(0), commands.amax(0)

    def support_score(self, commands: torch.Tensor | Split) -> torch.Tensor:
        """Out-of-support score (n,) of servo commands (n, S) [mm] or a Split (:class:`~.uncertainty.SupportModel`;
        > 1: outside the training support, the prediction extrapolates)."""
        if self.support is None:
            raise ValueError("support_score: this model has no support model (saved without one)")
        split = commands if isinstance(commands, Split) else self.split(commands)
        return self.support(split.features[..., :2])


def _member_state(member: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in member.state_dict().items() if not k.startswith("cc.")}


def compositional_config(member: CCCompositionalResidual) -> dict[str, Any]:
    """The constructor arguments that shape a compositional member: context, width, depth, torsion."""
    linear = linear_layers(member.fk.net)
    return {"context": member.fk.front.context, "width": int(linear[0].out_features), "depth": len(linear) - 1,
            "torsion": bool(member.twist_mask[5] != 0)}


def _structure(members: list) -> str:
    """The members' structure, "clarke_residual" or "compositional" (all of one family, else a ValueError)."""
    for structure, cls in (("clarke_residual", CCClarkeResidual), ("compositional", CCCompositionalResidual)):
        if members and all(isinstance(m, cls) for m in members):
            return structure
    raise ValueError(f"members: expected CCClarkeResidual models (the CC Clarke-residual family) or "
                     f"CCCompositionalResidual models, all of one kind, got {[type(m).__name__ for m in members]}")


def save_hardware_model(model: HardwareModel, path: str | Path) -> Path:
    """Write ``model`` as a weights-only checkpoint (format of the module docstring); returns the path."""
    structure = _structure(model.members)
    if structure == "compositional" and model.history:
        raise ValueError(f"members: compositional models with history inputs ({model.name!r}) cannot be saved yet "
                         f"(no exported module passes their play state); save a static compositional model")
    extra = {} if structure == "clarke_residual" else {
        "structure": structure, "compositional": compositional_config(model.members[0])}
    if extra and any(compositional_config(m) != extra["compositional"] for m in model.members):
        raise ValueError(f"members: expected compositional members of one shape, got "
                         f"{[compositional_config(m) for m in model.members]}")
    blob = {"format": FORMAT if not extra else FORMAT_COMPOSITIONAL, **extra,
            "model": model.name, "history": model.history, "play_width": float(model.play_width),
            "robot": model.spec.to_dict(), "servo_map": model.smap.to_dict(), "servo_ids": list(model.servo_ids),
            "units": "mm", "cc": {k: v.detach().clone() for k, v in model.cc.state_dict().items()},
            "members": [_member_state(m) for m in model.members],
            "sigma_calibration": None if model.sigma is None else
            {"scale": float(model.sigma.scale), "floor": float(model.sigma.floor)},
            "sigma_model": None if model.sigma_model is None else model.sigma_model.to_dict(),
            "support": None if model.support is None else dict(model.support.state_dict()),
            "examples": None if model.examples is None else model.examples.detach().double().clone(),
            "info": model.info}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(blob, path)
    return path


def load_hardware_model(path: str | Path) -> HardwareModel:
    """Load a checkpoint written by :func:`save_hardware_model` (``weights_only=True``); ValueError naming the file
    for anything else (another file type or format version, missing entries, weights that do not fit the robot)."""
    return hardware_model_from_blob(load_torch_file(path, "a weights-only hardware model checkpoint"), path)


def is_hardware_blob(blob: Any) -> bool:
    """True for the loaded content of a file written by :func:`save_hardware_model`."""
    return isinstance(blob, dict) and blob.get("format") in FORMATS


def hardware_model_from_blob(blob: Any, path: str | Path) -> HardwareModel:
    """The model in a checkpoint's loaded content (``path`` names the file in errors)."""
    if not is_hardware_blob(blob):
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise ValueError(f"{path}: expected a hardware model checkpoint of format {' or '.join(FORMATS)}, "
                         f"got {got!r}")
    keys = _KEYS + (("structure", "compositional") if blob["format"] == FORMAT_COMPOSITIONAL else ())
    missing = [k for k in keys if k not in blob]
    if missing:
        raise ValueError(f"{path}: hardware model checkpoint lacks the entries {missing}")
    research = {k: blob[k] for k, off in (("clamp", False), ("gate_width", None)) if blob.get(k, off) != off}
    if research:
        raise ValueError(f"{path}: the members were fitted with the research options {research} (support clamp, "
                         f"fallback gate), which this version no longer runs; refit the model without them")
    try:
        return _build(blob)
    except (RuntimeError, KeyError, TypeError, IndexError) as err:
        raise ValueError(f"{path}: the stored weights do not fit the stored robot ({type(err).__name__}: "
                         f"{str(err)[:300]})") from None


class ModelFile(NamedTuple):
    """A model file read once (:func:`read_model_file`): ``path``, ``blob`` (its weights-only content) and
    ``hardware``: a saved hardware model (:func:`hardware_model_from_blob`), else a ``train.py`` checkpoint
    (:func:`dacr_learn.runs.load_model` with ``blob``)."""

    path: Path
    blob: Any
    hardware: bool


def read_model_file(path: str | Path) -> ModelFile:
    """The checkpoint ``path`` names (a file, a ``train.py`` run or version folder:
    :func:`~dacr_learn.runs.find_checkpoint`), loaded once (``weights_only``) and recognised by its contents.
    FileNotFoundError / ValueError naming the path when there is none or it is not a torch file."""
    ckpt = find_checkpoint(path)
    blob = load_torch_file(ckpt, CHECKPOINT)
    return ModelFile(ckpt, blob, is_hardware_blob(blob))


def _support_from_state(state: dict, m: int) -> SupportModel:
    support = SupportModel(m)
    support.load_state_dict(state)
    return support


def _build(blob: dict) -> HardwareModel:
    spec = RobotSpec.from_dict(blob["robot"])
    smap = ServoMap.from_dict(blob["servo_map"])
    ids = tuple(blob["servo_ids"])
    smap.check(spec, ids)
    cc = CalibratedCC.from_state_dict(spec, blob["cc"])   # axial or lateral marker, as saved
    cc.requires_grad_(False)
    members = [_member(blob, state, cc) for state in blob["members"]]
    if not members:
        raise ValueError("members: the checkpoint holds no ensemble member")
    cal, sigma_model = blob.get("sigma_calibration"), blob.get("sigma_model")
    support = blob.get("support")
    return HardwareModel(blob["model"], spec, smap, ids, cc, members, float(blob["play_width"]),
                         None if cal is None else SigmaCalibration(cal["scale"], cal["floor"]),
                         None if support is None else _support_from_state(support, spec.num_segments),
                         blob.get("examples"), dict(blob.get("info") or {}),
                         None if sigma_model is None else SigmaModel.from_dict(sigma_model))


def _member(blob: dict, state: dict, cc: CalibratedCC) -> nn.Module:
    """One ensemble member of a checkpoint, built from the stored shapes around the shared CC model and loaded
    (strict: the state dict holds every buffer a fit sets)."""
    if blob["format"] == FORMAT_COMPOSITIONAL:
        if blob["structure"] != "compositional" or blob["history"]:
            raise ValueError(f"structure: expected 'compositional' without history, got {blob['structure']!r} "
                             f"with history={blob['history']!r}")
        member = CCCompositionalResidual(cc, **blob["compositional"])
    else:
        member = (CCClarkeResidualHistory if blob["history"] else CCClarkeResidual)(cc)
        if blob["format"] == FORMAT_V1:
            state = {k: v for k, v in state.items() if k not in _V1_BUFFERS}
    member.load_state_dict({**state, **{f"cc.{k}": v for k, v in cc.state_dict().items()}})
    return member.eval()


def support_warning(model: HardwareModel, setup_split: Split, what: str = "val") -> str | None:
    """A warning line when commands of a split lie outside the training support (score > 1), else None."""
    score = model.support(setup_split.features[..., :2])
    out = int((score > 1).sum())
    if out == 0:
        return None
    return (f"warning: {out} of {len(score)} {what} commands ({100 * out / len(score):.1f} %) lie outside the "
            f"training support (out-of-support score > 1, max {float(score.max()):.1f}): predictions there "
            "extrapolate")
