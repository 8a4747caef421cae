"""Export of a saved hardware model (:mod:`.checkpoint`) with ``python -m dacr_learn.export``.

The same kind of files as for the synthetic FK models, written and verified by the same code
(:mod:`dacr_learn.deploy.export`), ``metadata.json`` with task ``"hardware_fk"``, the servo ids and map.
Modules (:mod:`.inference`; their inputs and outputs: :func:`signatures`, docs/export.md "Hardware models"):
``fk``, ``jacobian`` and, for history models, ``initial_state``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ...deploy import export as dexport
from .checkpoint import HardwareModel, load_hardware_model
from .compositional_inference import CompositionalHardwareFK, CompositionalHardwareJacobian
from .inference import HardwareFK, HardwareJacobian, InitialState

TASK = "hardware_fk"
UNITS = {"servo": "mm (commanded tendon displacement, columns in servo_ids order)",
         "tip": "m (motion-capture frame)", "tip_std": "m (ensemble spread, calibrated if the checkpoint says so)",
         "jacobian": "m/mm, d tip / d servo (rows x, y, z; columns servo_ids)",
         "state": "m (play operator state per segment, Clarke coordinates)"}


def modules(model: HardwareModel, dtype: torch.dtype) -> dict[str, nn.Module]:
    if model.compositional:                        # the compositional CC model: static, no state
        return {"fk": CompositionalHardwareFK(model, dtype).eval(),
                "jacobian": CompositionalHardwareJacobian(model, dtype).eval()}
    fk = HardwareFK(model, dtype).eval()
    out = {"fk": fk, "jacobian": HardwareJacobian(model, dtype).eval()}
    if model.history:
        out["initial_state"] = InitialState(fk).eval()
    return out


def signatures(model: HardwareModel) -> dict[str, dict[str, list]]:
    s, m = len(model.servo_ids), model.spec.num_segments
    state = [["state", [m, 2]]] if model.history else []
    return {"fk": {"inputs": [["servo", [s]]] + state, "outputs": [["tip", [3]], ["tip_std", [3]]] + state},
            "jacobian": {"inputs": [["servo", [s]]] + state, "outputs": [["tip", [3]], ["J", [3, s]]] + state},
            "initial_state": {"inputs": [["servo", [s]]], "outputs": state}}


def examples(model: HardwareModel, dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
    """Commands (n, S) [mm] and, for history models, play states near those before each (run causally)."""
    servo = model.examples if model.examples is not None else torch.zeros(4, len(model.servo_ids))
    servo = servo.to(torch.float64)
    if not model.history:
        return servo.to(dtype), None
    ref = HardwareFK(model, torch.float64)
    states, state = [], ref.initial_state(servo[:1])
    with torch.no_grad():
        for t in range(servo.shape[0]):
            states.append(state)
            state = ref(servo[t:t + 1], state)[2]
    # Off the play operator's kink: after a drag the state lies exactly at the play width from the
    # command, where the Jacobian is one-sided and float32/float64 may take different sides.
    g = torch.Generator().manual_seed(0)
    states = torch.cat(states) + 0.3 * model.play_width * torch.randn(servo.shape[0], *states[0].shape[1:],
                                                                       generator=g, dtype=torch.float64)
    return servo.to(dtype), states.to(dtype)


def export_hardware(ckpt: str | Path, out: str | Path, *, dtype: torch.dtype = torch.float32,
                    aoti: bool | tuple[str, ...] = True, model: HardwareModel | None = None,
                    autotune: bool = False) -> dict[str, Any]:
    """Export a hardware checkpoint's modules to ``out``; returns the metadata (also written).
    ``model``: the checkpoint's model when the caller has loaded it already (not loaded again);
    ``autotune``: AOTInductor packages with :data:`dacr_learn.deploy.export.AUTOTUNE_CONFIGS`."""
    ckpt = Path(ckpt)
    model = model if model is not None else load_hardware_model(ckpt)
    out = dexport.output_folder(out)
    servo, state = examples(model, dtype)
    sig = signatures(model)
    meta: dict[str, Any] = {
        **dexport.export_header(ckpt, TASK, dtype, autotune), "model": model.name, "history": model.history,
        "ensemble_members": len(model.members), "robot": model.spec.to_dict(), "features": "clarke",
        "servo_ids": list(model.servo_ids), "servo_map": model.smap.to_dict(), "units": UNITS}
    exported = modules(model, dtype)
    meta["modules"] = {name: dict(sig[name]) for name in exported}
    inputs = {name: (servo,) if name == "initial_state" or state is None else (servo, state) for name in exported}
    # fk / initial_state against the float64 model. The Jacobian jumps where a tendon is exactly at its
    # slack onset or the play state at its width (one-sided derivatives; float32 and float64 may pick
    # different sides), so it is compared with the same module in the export's dtype.
    reference, same_dtype = modules(model, torch.float64), modules(model, dtype)
    references = {name: same_dtype[name] if name == "jacobian" else _in_float64(reference[name]) for name in exported}
    return dexport.write_export(out, meta, exported, inputs, references, aoti=aoti, autotune=autotune,
                                against="the hardware model")


def _in_float64(module: nn.Module):
    return lambda *xs: module(*(x.double() for x in xs))
