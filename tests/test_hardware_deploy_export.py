"""Export of hardware checkpoints (dacr_learn.hardware.deploy.export through python -m dacr_learn.export): the exported
modules equal the library model, stored as whole tensors.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import first_pass_export, roundoff_tol
from hardware_testkit import (
    IDS,
    TIP_SCALE,
    V4_TIP_SCALE,
    batch_prediction,
    command_recording,
    export_recording_warnings,
    sigma_roundoff_tol,
    v4_commands,
)

from dacr_learn import export as dexport
from dacr_learn.hardware.deploy.checkpoint import load_hardware_model, save_hardware_model
from dacr_learn.hardware.deploy.compositional_inference import CompositionalHardwareJacobian
from dacr_learn.hardware.deploy.inference import HardwareJacobian

pytestmark = pytest.mark.usefixtures("one_thread")


def test_export_of_a_hardware_checkpoint_equals_the_model(history_export):
    model, ckpt, out, meta, *_ = history_export
    assert meta["task"] == "hardware_fk" and meta["servo_ids"] == list(IDS)
    assert set(meta["modules"]) == {"fk", "jacobian", "initial_state"}
    assert max(meta["max_abs_deviation"].values()) <= dexport.VERIFY_TOLERANCE
    fk = dexport.load(out, "fk", checkpoint=ckpt)
    rec = command_recording(80, 11)
    servo = (1e3 * rec.servo).float()
    init = dexport.load(out, "initial_state")
    state, tips = init(servo[:1]), []
    for t in range(servo.shape[0]):                      # the controller's causal loop
        tip, std, state = fk(servo[t:t + 1], state)
        tips.append(tip)
    assert (torch.cat(tips).double() - batch_prediction(model, rec)).abs().max() <= roundoff_tol(
        torch.float32, TIP_SCALE, ulps=256)
    jac = dexport.load(out, "jacobian")
    # not the last command: the final state lies exactly at the play width from it, where J is one-sided
    # (float32 and float64 may take different sides)
    ref = HardwareJacobian(model, torch.float64)(servo[:-1].double(), state.double().expand(79, -1, -1))
    got = jac(servo[:-1], state.expand(79, -1, -1))
    assert (got[1].double() - ref[1]).abs().max() <= roundoff_tol(torch.float32, float(ref[1].abs().max()), 4096)
    with pytest.raises(ValueError, match="inputs must share their batch dims"):
        fk(servo[:3], state)
    with pytest.raises(ValueError, match="fk input state: expected shape"):
        fk(servo[:1], state[..., :1])


@pytest.fixture(scope="module")
def exported_compositional(request, tmp_path_factory):
    """(checkpoint, export folder, metadata, warnings) of the distal compositional test ensemble, saved and exported
    (conftest.first_pass_export: under make test the second pass runs the first pass's export)."""
    def make(out: Path) -> dict:
        ckpt = save_hardware_model(request.getfixturevalue("compositional_models")["distal"], out / "model.pt")
        meta, caught = export_recording_warnings(ckpt, out / "export")
        return {"meta": meta, "caught": caught}

    out, record = first_pass_export("compositional_export", make, tmp_path_factory)
    return out / "model.pt", out / "export", record["meta"], record["caught"]


def test_export_equals_the_eager_model(v4_slice, exported_compositional):
    ckpt, out, meta, _ = exported_compositional
    model = load_hardware_model(ckpt)                        # the distal ensemble, as saved (a lossless round trip)
    assert meta["task"] == "hardware_fk" and not meta["history"] and set(meta["modules"]) == {"fk", "jacobian"}
    assert max(meta["max_abs_deviation"].values()) <= dexport.VERIFY_TOLERANCE
    servo = v4_commands(v4_slice).float()
    tip, std = dexport.load(out, "fk", checkpoint=ckpt)(servo)
    ref_tip, ref_std = model.predict(servo.double())
    assert (tip.double() - ref_tip).abs().max() <= roundoff_tol(torch.float32, V4_TIP_SCALE, ulps=128)
    assert (std.double() - ref_std).abs().max() <= sigma_roundoff_tol(model, torch.float32, V4_TIP_SCALE, ulps=128)
    jac = dexport.load(out, "jacobian")
    got = jac(servo)[1]
    ref = CompositionalHardwareJacobian(model, torch.float64)(servo.double())[1]
    assert (got.double() - ref).abs().max() <= roundoff_tol(torch.float32, float(ref.abs().max()), ulps=4096)
    batched = jac(servo.reshape(4, 6, 9))[1]                   # leading batch dims
    assert batched.shape == (4, 6, 3, 9)
    with pytest.raises(ValueError, match="fk input servo: expected shape"):
        dexport.load(out, "fk")(servo[:, :5])
    assert Path(out / dexport.METADATA_FILE).exists()


@pytest.mark.parametrize("exported", ["history_export", "exported_compositional"])
def test_hardware_export_stores_whole_tensors(exported, request):
    """torch.export.save warned "No complete tensor found in the group!" for every exported hardware module:
    their stacked weights were transposed views. Fixed at the source: the modules' buffers are contiguous.
    The warnings of the two shared exports (a residual ensemble with history through HardwareFK, a compositional
    one through CompositionalHardwareFK), recorded while they were written."""
    caught = request.getfixturevalue(exported)[-1]
    assert not [message for message in caught if "complete tensor" in message]
