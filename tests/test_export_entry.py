"""The one export entry (dacr_learn.export): no Lightning where the checkpoint names its whole architecture,
the Lightning fallback where it does not, one-line errors naming --out, a missing export folder named.

The checkpoints are the tiny ones written by main at 87f426b (tests/data/main_87f426b).
"""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import ROOT, names

from dacr_learn import export as dexport
from dacr_learn.cli import export as export_cli
from dacr_learn.console import run_cli
from dacr_learn.runs import load_checkpoint_model

pytestmark = pytest.mark.usefixtures("one_thread")

DATA = ROOT / "tests" / "data" / "main_87f426b"


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)


# a fresh interpreter exports two models (~25 s): in the rest's process, which ends ~45 s before the slow one
def test_export_and_load_import_no_lightning_and_the_fallback_does(tmp_path):
    """A train.py checkpoint and a hardware model are exported and loaded without importing Lightning; a
    checkpoint whose hyper-parameters lack part of the architecture is read through its LightningModule (the
    positive control: it does import Lightning) and gives the same model. One fresh interpreter for all (each
    start-up imports torch: seconds)."""
    blob = torch.load(DATA / "fk.ckpt", weights_only=True)
    del blob["hyper_parameters"]["activation"]               # the FKModule default ("silu") fills it in
    torch.save(blob, tmp_path / "old.ckpt")
    task, model = load_checkpoint_model(tmp_path / "old.ckpt")
    _, direct = load_checkpoint_model(DATA / "fk.ckpt")
    q = torch.load(DATA / "outputs.pt", weights_only=True)["fk"]["input"].float()
    with torch.no_grad():
        assert task == "fk" and torch.equal(model(q), direct(q))
    run = _run(f"""
import sys
from dacr_learn.export import export_checkpoint, load
from dacr_learn.runs import load_checkpoint_model
for ckpt in ("fk.ckpt", "hardware_model.pt"):
    meta = export_checkpoint({str(DATA)!r} + "/" + ckpt, {str(tmp_path)!r} + "/" + ckpt, aoti=False)
    load({str(tmp_path)!r} + "/" + ckpt, "fk")
    print(meta["task"], sorted(m for m in sys.modules if m.split(".")[0] in ("lightning", "pytorch_lightning")))
load_checkpoint_model({str(tmp_path / 'old.ckpt')!r})
print("lightning" in sys.modules)
""")
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == ["fk []", "hardware_fk []", "True"], run.stdout
    # the hardware model written by main exports (test_legacy_checkpoints.py checks that it loads and predicts)
    meta = dexport.read_metadata(tmp_path / "hardware_model.pt")
    assert meta["task"] == "hardware_fk" and set(meta["modules"]) == {"fk", "jacobian", "initial_state"}
    assert max(meta["max_abs_deviation"].values()) <= dexport.VERIFY_TOLERANCE


@pytest.mark.parametrize("where", ["a file", "below a file"])
def test_out_blocked_by_a_file_is_one_line_naming_out(where, tmp_path, capsys):
    """In process through run_cli, what ``python -m dacr_learn.export`` runs (its entry point: test_export.py's
    test_export_cli_prints_the_error_not_a_traceback): a subprocess here cost 5 s of imports per case."""
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" if where == "a file" else tmp_path / "afile" / "sub"
    code = run_cli(export_cli.main, ["--ckpt", str(DATA / "fk.ckpt"), "--out", str(out), "--no-aoti"])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"error: --out {out}: ") and "expected a folder" in lines[0], err
    assert (tmp_path / "afile").read_text() == "x"                                  # left as it was


def test_out_with_missing_parents_is_created(tmp_path):
    out = tmp_path / "new" / "deeper" / "export"
    meta = export_cli.main(["--ckpt", str(DATA / "ik.ckpt"), "--out", str(out), "--no-aoti"])
    assert meta["task"] == "ik" and (out / dexport.METADATA_FILE).is_file()


def test_loading_a_missing_export_names_the_folder(tmp_path):
    missing = tmp_path / "exports" / "nope"
    with pytest.raises(FileNotFoundError, match=names(missing, "no such export folder")) as err:
        dexport.load(missing, "fk")
    assert str(missing / dexport.METADATA_FILE) not in str(err.value)
    (tmp_path / "empty").mkdir()                                                    # a folder, but no export
    with pytest.raises(FileNotFoundError, match=names(tmp_path / "empty" / dexport.METADATA_FILE)):
        dexport.load(tmp_path / "empty", "fk")
