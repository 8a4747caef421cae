"""RobotSpec: parsing, validation (every error names its field), dict/YAML round trips."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
import yaml
from conftest import FAST, ROBOT_CONFIGS, TYPE1, names, robot_dicts, roundoff_tol
from hypothesis import given

from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.robot import DEFAULT_BEND, MAX_LAYOUT_CONDITION, RobotSpec
from dacr_learn.training import FKModule

pytestmark = pytest.mark.usefixtures("one_thread")


def base_robot() -> dict:
    return {
        "name": "t",
        "routing": "independent",
        "segments": [
            {"type": "I", "length": 0.1, "radius": 0.008, "joints": 4, "offset": 0.0,
             "limits": {"bend": 1.0, "length": [0.08, 0.12]}},
            {"type": "0", "length": 0.09, "radius": 0.007, "joint_angles": [0.0, 2.0, 4.0],
             "joint_radii": [0.007, 0.006, 0.008], "limits": {"bend": 1.2}},
        ],
    }


def mutated(path: tuple, value, delete: bool = False) -> dict:
    """base_robot() with the entry at ``path`` replaced (or deleted)."""
    d = copy.deepcopy(base_robot())
    node = d
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


def collinear_layout_extending() -> dict:
    """An extending segment whose joints lie on the line x = d (unequal radii).

    Then (d_i/d)·cos ψ_i = 1 for every joint: the first column of A equals 1, so A has full
    rank 2 but [A, 1] has rank 2 < 3 and the length cannot be told from bending.
    """
    d, ys = 0.008, np.array([-0.006, 0.001, 0.004, 0.009])
    seg = {"type": "I", "length": 0.1, "radius": d,
           "joint_angles": np.arctan2(ys, d).tolist(), "joint_radii": np.hypot(d, ys).tolist()}
    return {"segments": [seg]}


INVALID = [
    # (description dict, substring the message must contain)
    (mutated(("colour",), "red"), "colour"),
    (mutated(("segments", 0, "stiffness"), 1.0), "stiffness"),
    (mutated(("segments", 0, "limits", "speed"), 1.0), "speed"),
    (mutated(("segments", 1, "limits", "length"), [0.08, 0.1]), "segments[1].limits"),   # type 0 does not extend
    (mutated(("segments", 0, "limits", "twist"), [-1, 1]), "segments[0].limits"),        # type I does not twist
    (mutated(("segments", 0, "type"), "IV"), "segments[0].type"),
    (mutated(("segments", 0, "type"), 1), "segments[0].type"),
    (mutated(("segments", 0, "length"), "0.1"), "segments[0].length"),
    (mutated(("segments", 0, "length"), True), "segments[0].length"),
    (mutated(("segments", 0, "length"), 0.0), "segments[0].length"),
    (mutated(("segments", 0, "length"), -0.1), "segments[0].length"),
    (mutated(("segments", 0, "length"), math.inf), "segments[0].length"),
    (mutated(("segments", 0, "length"), None, delete=True), "segments[0].length"),
    (mutated(("segments", 0, "radius"), 0), "segments[0].radius"),
    (mutated(("segments", 0, "radius"), -0.008), "segments[0].radius"),
    (mutated(("segments", 1, "joint_radii"), [0.007, -0.006, 0.008]), "segments[1].joint_radii"),
    (mutated(("segments", 1, "joint_radii"), [0.007, 0.006]), "segments[1].joint_radii"),
    (mutated(("segments", 1, "joint_angles"), [0.0, "a", 4.0]), "segments[1].joint_angles"),
    (mutated(("segments", 1, "joint_angles"), 1.0), "segments[1].joint_angles"),
    (mutated(("segments", 0, "joints"), 2), "segments[0].joints"),
    (mutated(("segments", 0, "joints"), 4.0), "segments[0].joints"),
    (mutated(("segments", 0, "joints"), "4"), "segments[0].joints"),
    (mutated(("segments", 1, "joint_angles"), [0.0, 2.0]), "segments[1].joint_angles"),   # n < 3
    (mutated(("segments", 0, "offset"), "zero"), "segments[0].offset"),
    (mutated(("segments", 0, "limits", "bend"), 0.0), "segments[0].limits.bend"),
    (mutated(("segments", 0, "limits", "bend"), 4.0), "segments[0].limits.bend"),
    (mutated(("segments", 0, "limits", "length"), [0.12, 0.08]), "segments[0].limits.length"),
    (mutated(("segments", 0, "limits", "length"), [-0.1, 0.08]), "segments[0].limits.length"),
    (mutated(("segments", 0, "limits"), [1.0]), "segments[0].limits"),
    (mutated(("routing",), "serial"), "routing"),
    (mutated(("name",), 3), "name"),
    (mutated(("segments",), []), "segments"),
    (mutated(("segments",), "none"), "segments"),
    (mutated(("segments", 0), 5), "segments[0]"),
    # rank-deficient layouts: all joints at one angle; all on one line through the centre
    (mutated(("segments", 1, "joint_angles"), [1.0, 1.0, 1.0]), "segments[1].joint_angles"),
    (mutated(("segments", 1, "joint_angles"), [0.5, 0.5 + math.pi, 0.5]), "segments[1].joint_angles"),
    # [A, 1] rank deficient for an extending segment with unequal radii
    (collinear_layout_extending(), "segments[0].joint_angles"),
    # twisting segment with unequal radii
    ({"segments": [{"type": "II", "length": 0.1, "radius": 0.008, "joint_angles": [0, 2, 4],
                    "joint_radii": [0.008, 0.007, 0.008]}]}, "segments[0].joint_radii"),
    # coupled routing through a twisting segment (the proximal one twists)
    ({"routing": "coupled", "segments": [
        {"type": "III", "length": 0.1, "radius": 0.008, "joints": 3},
        {"type": "0", "length": 0.1, "radius": 0.008, "joints": 3}]}, "segments[0].type"),
    # joints/offset together with joint_angles
    (mutated(("segments", 1, "joints"), 3), "segments[1]"),
    (mutated(("segments", 0, "joint_radii"), [0.008] * 4), "segments[0].joint_radii"),
]


def test_base_robot_is_valid():
    spec = RobotSpec.from_dict(base_robot())
    assert spec.num_segments == 2 and spec.num_joints == 7 and spec.num_actuated_features == 5


@pytest.mark.parametrize("desc,field", INVALID, ids=[f"{i}-{f}" for i, (_, f) in enumerate(INVALID)])
def test_invalid_description_raises_value_error_naming_field(desc, field):
    with pytest.raises(ValueError) as err:
        RobotSpec.from_dict(desc)
    assert field in str(err.value), f"message {str(err.value)!r} does not name {field!r}"


def test_collinear_extending_layout_is_rank_deficient_in_numpy():
    """Guard of the fixture above: A has full rank 2, [A, 1] only rank 2 (independently checked)."""
    seg = collinear_layout_extending()["segments"][0]
    psi, r = np.array(seg["joint_angles"]), np.array(seg["joint_radii"])
    a = (r / seg["radius"])[:, None] * np.stack([np.cos(psi), np.sin(psi)], 1)
    assert np.linalg.matrix_rank(a) == 2
    assert np.linalg.matrix_rank(np.c_[a, np.ones(len(psi))]) == 2
    # the same layout is fine for a non-extending segment
    RobotSpec.from_dict({"segments": [dict(seg, type="0")]})


def test_coupled_routing_allows_twist_in_last_segment_only():
    segs = [{"type": "I", "length": 0.1, "radius": 0.008, "joints": 4},
            {"type": "III", "length": 0.1, "radius": 0.008, "joints": 3}]
    spec = RobotSpec.from_dict({"routing": "coupled", "segments": segs})
    assert spec.num_joints == 4 + 3 + 1


def test_defaults_and_explicit_layout():
    spec = RobotSpec.from_dict({"segments": [{"type": "III", "length": 0.1, "radius": 0.01, "joints": 5,
                                              "offset": 0.3}]})
    seg = spec.segments[0]
    assert spec.routing == "independent"
    assert seg.bend == pytest.approx(DEFAULT_BEND)
    assert seg.length_range == pytest.approx((0.08, 0.12))
    assert seg.twist_range == pytest.approx((-math.pi / 2, math.pi / 2))
    expected = 0.3 + 2 * math.pi * np.arange(5) / 5
    assert np.allclose(seg.joint_angles, expected, atol=roundoff_tol(torch.float64, 2 * math.pi), rtol=0)
    assert seg.joint_radii == (0.01,) * 5


@FAST
@given(robot_dicts())
def test_dict_round_trip(d):
    spec = RobotSpec.from_dict(d)
    again = RobotSpec.from_dict(spec.to_dict())
    assert again == spec
    # and through YAML text
    assert RobotSpec.from_dict(yaml.safe_load(yaml.safe_dump(spec.to_dict()))) == spec


def test_yaml_file_round_trip(tmp_path):
    spec = RobotSpec.from_dict(base_robot())
    spec.to_yaml(tmp_path / "r.yaml")
    assert RobotSpec.from_yaml(tmp_path / "r.yaml") == spec


def test_robot_configs_exist():
    assert len(ROBOT_CONFIGS) >= 5


@pytest.mark.parametrize("path", ROBOT_CONFIGS, ids=[p.stem for p in ROBOT_CONFIGS])
def test_every_robot_config_loads(path):
    raw = yaml.safe_load(path.read_text())
    spec = RobotSpec.from_yaml(path)
    assert spec.name == raw["name"] and spec.routing == raw.get("routing", "independent")
    assert spec.num_segments == len(raw["segments"])
    for seg, seg_raw in zip(spec.segments, raw["segments"], strict=True):
        assert seg.type == seg_raw["type"] and seg.length == seg_raw["length"]
        n = seg_raw.get("joints", len(seg_raw.get("joint_angles", [])))
        assert seg.num_joints == n
    assert RobotSpec.from_dict(spec.to_dict()) == spec


@pytest.mark.parametrize("layout", [{"joints": 2}, {"joint_angles": [0.0, 2.0]}], ids=["joints", "joint_angles"])
def test_fewer_than_three_joints_message(layout):
    with pytest.raises(ValueError, match="at least 3 joints"):
        RobotSpec.from_dict({"segments": [{"type": "0", "length": 0.1, "radius": 0.008, **layout}]})


# --------------------------------------------------------------------------------------------------
# Robot YAML: a broken file gives a ValueError naming the file (and field)
# --------------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------------
# Joint layouts: numerically singular ones are refused, with the condition number found
# --------------------------------------------------------------------------------------------------


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
