"""Servo maps (dacr_learn.hardware.servo_map): column order, signs and zeros, the YAML round trip, missing slots;
a broken servo-map YAML gives a ValueError naming the file and field."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import names

from dacr_learn.hardware.servo_map import ServoAssignment, ServoMap

pytestmark = pytest.mark.usefixtures("one_thread")


def test_servo_map_reorders_signs_and_round_trips(tmp_path, v4_spec, v4_pulls):
    ids = v4_pulls.servo_ids
    servos = tuple(ServoAssignment(sid, k % 3, k // 3, sign=-1 if k == 4 else 1, zero=1e-3 * k)
                   for k, sid in enumerate(ids))
    smap = ServoMap(v4_spec.name, servos, -0.01)
    smap.to_yaml(tmp_path / "map.yaml")
    assert ServoMap.from_yaml(tmp_path / "map.yaml") == smap
    x = smap.displacements(v4_spec, v4_pulls)
    # joint (segment j, joint i) is column 3i + j here
    for j in range(3):
        for i in range(3):
            k = 3 * i + j
            expected = (-1 if k == 4 else 1) * (v4_pulls.servo[:, k] - 1e-3 * k)
            assert torch.allclose(x[:, 3 * j + i], expected)
    assert torch.allclose(smap.servo_values(v4_spec, ids, x), v4_pulls.servo)
    broken = ServoMap(v4_spec.name, servos[:-1] + (ServoAssignment(ids[-1], 0, 0),), -0.01)
    with pytest.raises(ValueError, match="slots missing"):
        broken.check(v4_spec)


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
