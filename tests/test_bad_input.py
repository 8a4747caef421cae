"""Users' files that are broken give a ValueError naming the file (and field), what was expected
and what was found, with the original error chained; a missing file a FileNotFoundError naming it.

Covered: robot YAML (syntax, empty, wrong top-level type, not UTF-8, a directory, a bad field),
numerically singular joint layouts (condition number), checkpoints given to export (not a torch
file, truncated, not a Lightning checkpoint of ours, bad robot spec, weights that do not fit),
dataset files (truncated tensors.pt, broken meta.json) and an export's metadata.json.
"""
from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dacr_learn import data as ddata
from dacr_learn import export as dexport
from dacr_learn.checks import check_tensor
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.robot import MAX_LAYOUT_CONDITION, RobotSpec
from dacr_learn.training import FKModule

ROOT = Path(__file__).resolve().parents[1]
TYPE1 = ROOT / "configs" / "robots" / "type1.yaml"

pytestmark = pytest.mark.usefixtures("one_thread")


def names(path: Path, *parts: str) -> str:
    """Regex that the message starts with the file and contains every part, in order."""
    return "^" + ".*".join(re.escape(p) for p in (str(path), *parts))


def truncated(path: Path, keep: int) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep >= 0 else data[:len(data) + keep])
    return path


# ------------------------------------------------------------------------------------------
# Robot YAML
# ------------------------------------------------------------------------------------------

BAD_YAML = {
    "syntax": ("name: x\nsegments: [\n  - {type: I", ("expected a robot description", "invalid YAML", "line 3")),
    "empty": ("", ("expected a robot description", "found an empty file")),
    "comments only": ("# nothing here\n", ("found an empty file",)),
    "list": ("- 1\n- 2\n", ("robot: got [1, 2]", "expected a mapping")),
    "string": ("just a sentence\n", ("robot: got 'just a sentence'", "expected a mapping")),
    "bad field": ("segments:\n  - {type: I, length: -0.1, radius: 0.008, joints: 4}\n",
                  ("segments[0].length", "got -0.1", "expected a finite number > 0")),
}


@pytest.mark.parametrize("case", BAD_YAML)
def test_robot_yaml_errors_name_the_file(tmp_path, case):
    text, parts = BAD_YAML[case]
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=names(path, *parts)) as err:
        RobotSpec.from_yaml(path)
    if case in ("syntax", "list", "bad field"):
        assert err.value.__cause__ is not None            # the original error is chained


def test_robot_yaml_unreadable_or_missing(tmp_path):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match=names(binary, "cannot be read as UTF-8", "UnicodeDecodeError")):
        RobotSpec.from_yaml(binary)
    with pytest.raises(ValueError, match=names(tmp_path, "cannot be read")):
        RobotSpec.from_yaml(tmp_path)                     # a directory
    with pytest.raises(FileNotFoundError, match=names(tmp_path / "nope.yaml", "no such file")):
        RobotSpec.from_yaml(tmp_path / "nope.yaml")


def test_coerce_accepts_spec_dict_and_path_and_names_bad_input(tmp_path):
    spec = RobotSpec.from_yaml(TYPE1)
    assert RobotSpec.coerce(spec) is spec
    assert RobotSpec.coerce(spec.to_dict()) == spec
    assert RobotSpec.coerce(str(TYPE1)) == spec == RobotSpec.coerce(TYPE1)
    with pytest.raises(ValueError, match="^robot: got 3, expected a RobotSpec"):
        RobotSpec.coerce(3)
    bad = tmp_path / "bad.yaml"
    bad.write_text("segments: [")
    with pytest.raises(ValueError, match=names(bad, "invalid YAML")):     # the Lightning entry points use coerce
        KinematicsDataModule(robot=str(bad))
    with pytest.raises(ValueError, match=names(bad, "invalid YAML")):
        FKModule(robot=str(bad))


# ------------------------------------------------------------------------------------------
# Joint layouts: numerically singular ones are refused, with the condition number found
# ------------------------------------------------------------------------------------------


def _numpy_condition(angles, extends: bool) -> float:
    """Independent reference: cond of A = [cos ψ, sin ψ] (and [A, 1]) with equal radii."""
    a = np.stack([np.cos(angles), np.sin(angles)], 1)
    return float(np.linalg.cond(np.c_[a, np.ones(len(angles))] if extends else a))


@pytest.mark.parametrize("seg_type", ["0", "I", "II", "III"])
@pytest.mark.parametrize("angles", [[0.0, math.pi, 0.0], [0.0, math.pi, 2 * math.pi], [0.0, 3.14159, 0.0],
                                    [1e-7, math.pi, 0.0], [0.0, math.pi - 1e-4, 0.0]])
def test_near_singular_layout_is_refused_with_its_condition_number(seg_type, angles):
    assert _numpy_condition(angles, seg_type in ("I", "III")) > MAX_LAYOUT_CONDITION    # guard of the fixture
    desc = {"segments": [{"type": seg_type, "length": 0.1, "radius": 0.008, "joint_angles": angles}]}
    with pytest.raises(ValueError, match=r"^segments\[0\]\.joint_angles: .*condition number <= 1e\+04.*"
                                         r"found cond\(\[?A(, 1\])?\) = ([0-9.e+]+|inf)$"):
        RobotSpec.from_dict(desc)


@pytest.mark.parametrize("delta", [1e-1, 1e-2, 1e-3, 1e-4, 1e-5])
def test_layout_condition_threshold_agrees_with_numpy(delta):
    """Joints at 0, π − δ, 0: cond(A) ≈ 2/δ; accepted exactly when numpy's cond ≤ MAX_LAYOUT_CONDITION."""
    angles = [0.0, math.pi - delta, 0.0]
    desc = {"segments": [{"type": "0", "length": 0.1, "radius": 0.008, "joint_angles": angles}]}
    if _numpy_condition(angles, False) <= MAX_LAYOUT_CONDITION:
        assert RobotSpec.from_dict(desc).segments[0].joint_angles == tuple(angles)
    else:
        with pytest.raises(ValueError, match=r"segments\[0\]\.joint_angles"):
            RobotSpec.from_dict(desc)


# ------------------------------------------------------------------------------------------
# Checkpoints given to export
# ------------------------------------------------------------------------------------------


def _checkpoint(**changes) -> dict:
    """A minimal Lightning checkpoint of an untrained FKModule (no Trainer needed)."""
    module = FKModule(robot=str(TYPE1), width=8, depth=1)
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "pytorch-lightning_version": "2.6.0"}
    for key, value in changes.items():
        if value is None:
            ckpt.pop(key)
        else:
            ckpt[key] = value
    return ckpt


def test_well_formed_checkpoint_loads(tmp_path):
    """Positive control for the refusals below: the same construction, unchanged, loads."""
    torch.save(_checkpoint(), tmp_path / "ok.ckpt")
    task, module = dexport.load_lightning_checkpoint(tmp_path / "ok.ckpt")
    assert task == "fk" and module.hparams.width == 8


def test_checkpoint_that_is_not_a_torch_file(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint at all\n" * 10)
    with pytest.raises(ValueError, match=names(garbage, "expected an FKModule/IKModule checkpoint",
                                               "found a file of 240 bytes", "not a complete torch.save")):
        dexport.load_lightning_checkpoint(garbage)
    for keep in (0, 1, 100, -10):
        torch.save(_checkpoint(), tmp_path / "cut.ckpt")
        cut = truncated(tmp_path / "cut.ckpt", keep)
        with pytest.raises(ValueError, match=names(cut, "not a complete torch.save archive")) as err:
            dexport.load_lightning_checkpoint(cut)
        assert err.value.__cause__ is not None
    with pytest.raises(FileNotFoundError, match=names(tmp_path / "missing.ckpt", "no such file")):
        dexport.load_lightning_checkpoint(tmp_path / "missing.ckpt")


def test_export_cli_prints_the_error_not_a_traceback(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match=names(garbage, "not a complete torch.save")):
        dexport.main(["--ckpt", str(garbage), "--out", str(tmp_path / "out")])
    run = subprocess.run([sys.executable, "-m", "dacr_learn.export", "--ckpt", str(garbage), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.returncode != 0 and "Traceback" not in run.stderr, run.stderr
    assert str(garbage) in run.stderr and "not a complete torch.save archive" in run.stderr, run.stderr
    assert "RuntimeWarning" not in run.stderr, run.stderr     # runpy: the package must not import its own CLI module


NOT_OURS = {   # case: (content of the torch file, parts of the message)
    "tensor": (lambda: torch.zeros(3), ("found a torch file holding a Tensor",)),
    "plain dict": (lambda: {"weights": torch.zeros(3)}, ("found a dict without", "state_dict", "hyper_parameters")),
    "no hyper-parameters": (lambda: _checkpoint(hyper_parameters=None), ("found a dict without", "hyper_parameters")),
    "no robot": (lambda: _checkpoint(hyper_parameters={"features": "clarke"}), ("without a robot spec",)),
    "bad robot": (lambda: _checkpoint(hyper_parameters={"robot": {"segments": []}}),
                  ("hyper_parameters.robot", "segments: got []", "expected a non-empty list")),
    "other weights": (lambda: _checkpoint(state_dict={"layer.weight": torch.zeros(2)}),
                      ("without model.front.norm / model.in_norm", "layer.weight")),
    "weights of another width": (
        lambda: _checkpoint(state_dict=FKModule(robot=str(TYPE1), width=16, depth=1).state_dict()),
        ("FKModule cannot load", "size mismatch")),
}


@pytest.mark.parametrize("case", NOT_OURS)
def test_torch_file_that_is_not_our_checkpoint(tmp_path, case):
    content, parts = NOT_OURS[case]
    path = tmp_path / "other.ckpt"
    torch.save(content(), path)
    with pytest.raises(ValueError, match=names(path, *parts)):
        dexport.load_lightning_checkpoint(path)


def test_export_metadata_that_is_not_json(tmp_path):
    meta = tmp_path / dexport.METADATA_FILE
    for text, found in (("{oops", "found invalid JSON"), ("[1, 2]", "found a JSON list")):
        meta.write_text(text)
        with pytest.raises(ValueError, match=names(meta, "expected the metadata.json of an export", found)):
            dexport.read_metadata(tmp_path)


# ------------------------------------------------------------------------------------------
# Dataset files
# ------------------------------------------------------------------------------------------


@pytest.fixture()
def dataset(tmp_path) -> tuple[Path, RobotSpec]:
    spec = RobotSpec.from_yaml(TYPE1)
    return ddata.save_dataset(tmp_path / "ds", spec, ddata.generate(spec, 16, seed=0), 0, ddata.SamplerOptions()), spec


@pytest.mark.parametrize("keep", [0, 1, 100, 0.5, -100, -10, -1])
def test_truncated_tensor_file(dataset, keep):
    """Truncations at every depth: torch raises EOFError, UnpicklingError, RuntimeError or OSError (EINVAL)."""
    directory, spec = dataset
    path = directory / ddata.TENSOR_FILE
    truncated(path, int(keep * path.stat().st_size) if isinstance(keep, float) else keep)
    with pytest.raises(ValueError, match=names(path, "expected the tensors.pt of a dataset", "found a file of",
                                               "not a complete torch.save archive")) as err:
        ddata.load_dataset(directory, spec)
    assert err.value.__cause__ is not None


def test_tensor_file_of_another_content(dataset):
    directory, spec = dataset
    path = directory / ddata.TENSOR_FILE
    torch.save([1, 2], path)
    with pytest.raises(ValueError, match=names(path, "a dict of named tensors", "found a list")):
        ddata.load_dataset(directory, spec)
    torch.save({"q": torch.zeros(2), "note": "text"}, path)
    with pytest.raises(ValueError, match=names(path, "not named tensors", "'note': 'str'")):
        ddata.load_dataset(directory, spec)


@pytest.mark.parametrize("text,found", [("{not json", "found invalid JSON"), ("[1, 2]", "found a JSON list"),
                                        ("", "found invalid JSON")])
def test_broken_meta_json(dataset, text, found):
    directory, spec = dataset
    path = directory / ddata.META_FILE
    path.write_text(text)
    with pytest.raises(ValueError, match=names(path, "expected the meta.json of a dataset", found)):
        ddata.load_dataset(directory, spec)
    with pytest.raises(ValueError, match=names(path, found)):       # a cache directory is not silently replaced
        ddata.generate_or_load(directory, spec, 16, 0)


def test_meta_json_with_a_bad_robot(dataset):
    directory, spec = dataset
    path = directory / ddata.META_FILE
    meta = json.loads(path.read_text())
    meta["robot"] = {"segments": "none"}
    path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=names(path, "segments: got 'none'")):
        ddata.load_dataset(directory, spec)


def test_check_tensor_nonempty_and_messages():
    check_tensor(torch.zeros(0, 3), "x", (3,))                  # empty batches are fine by default
    with pytest.raises(ValueError, match=r"^x: expected a non-empty batch, got shape \(0, 3\)$"):
        check_tensor(torch.zeros(0, 3), "x", (3,), nonempty=True)
    with pytest.raises(ValueError, match=r"^x: expected shape \(\.\.\., 3\), got a tensor of shape \(2, 2\)$"):
        check_tensor(torch.zeros(2, 2), "x", (3,))


# ---------------------------------------------------------------- hardware files

SERVO_MAP = "robot: r\nslack_level: -0.01\nservos:\n- {servo: '1', segment: 0, joint: 0}\n"


@pytest.mark.parametrize("text,found", [
    ("robot: [unclosed\n", "found invalid YAML"),
    (SERVO_MAP.replace("segment: 0", "segment: x"), "servos[0].segment: expected an integer, got 'x'"),
    (SERVO_MAP.replace("segment: 0", "segment: 0.5"), "servos[0].segment: expected an integer, got 0.5"),
    (SERVO_MAP.replace("-0.01", "low"), "slack_level: expected a number, got 'low'"),
    (SERVO_MAP + "calibration: [1]\n", "calibration: expected a mapping"),
])
def test_servo_map_yaml_errors_name_the_file_and_field(tmp_path, text, found):
    from dacr_learn.hardware.servo_map import ServoMap

    path = tmp_path / "map.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=names(path, found)):
        ServoMap.from_yaml(path)
    assert ServoMap.from_yaml(_written(tmp_path / "good.yaml", SERVO_MAP)).servos[0].servo == "1"


def _written(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_recording_that_is_not_utf8_or_missing(tmp_path):
    from dacr_learn.hardware.recording import load_recording

    path = tmp_path / "rec.csv"
    path.write_bytes(b"timestamp,pattern_label\n\xff\xfe,\x00\n")
    with pytest.raises(ValueError, match=names(path, "expected a recording CSV", "UTF-8")):
        load_recording(path)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "missing.csv"))):
        load_recording(tmp_path / "missing.csv")


@pytest.mark.parametrize("n", [3, 300])                       # below / above the Python-sum size (_PY_SUM_MAX)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "inf_and_minus_inf"])
def test_check_tensor_finiteness_on_both_sum_paths(n, dtype, bad):
    x = torch.ones(n, 3, dtype=dtype)
    if bad == "inf_and_minus_inf":                             # their sum is NaN, but each entry is caught
        x[0, 0], x[-1, 2] = math.inf, -math.inf
        count = 2
    else:
        x[n // 2, 1] = bad
        count = 1
    with pytest.raises(ValueError, match=rf"^q: expected finite values of shape \(\.\.\., 3\), got {count} NaN/inf"):
        check_tensor(x, "q", (3,))
    check_tensor(x, "q", (3,), finite=False)                   # the other checks still pass


@pytest.mark.parametrize("n", [3, 300])
def test_check_tensor_accepts_finite_values_whose_sum_overflows(n):
    x = torch.full((n, 3), torch.finfo(torch.float32).max, dtype=torch.float32)   # float32 sum: inf
    check_tensor(x, "q", (3,))
    check_tensor(torch.full((n, 3), 1e308, dtype=torch.float64), "q", (3,))          # float64 sum: inf
