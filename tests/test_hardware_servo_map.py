"""Servo maps (dacr_learn.hardware.servo_map): a broken servo-map YAML gives a ValueError naming the file and field."""
from __future__ import annotations

from pathlib import Path

import pytest
from conftest import names

pytestmark = pytest.mark.usefixtures("one_thread")


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
