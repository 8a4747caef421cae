"""RobotSpec: parsing, validation (every error names its field), dict/YAML round trips."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
import yaml
from conftest import FAST, ROBOT_CONFIGS, robot_dicts, roundoff_tol
from hypothesis import given

from dacr_learn.robot import DEFAULT_BEND, RobotSpec


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
