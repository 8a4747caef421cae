"""examples/track_port.py end to end (a short path), and the Rerun helpers of the arm (dacr_learn.viz.arm)."""
from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from conftest import load_example
from rerun_testkit import rrd_data, rrd_verify, rrd_views

from dacr_learn.viz.arm import capsules_between, log_arm, log_port

pytestmark = pytest.mark.usefixtures("one_thread")


def rotate_z(quat: np.ndarray) -> np.ndarray:
    """+z rotated by quaternions (k, 4) xyzw (the standard formula, written out)."""
    x, y, z, w = quat.T
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def test_capsules_join_consecutive_points_and_skip_coincident_ones():
    points = np.array([[0, 0, 0], [0, 0, 0.3], [0, 0, 0.3], [0.2, 0.1, 0.3], [0.2, 0.1, 0.1]], dtype=float)
    start, length, quat = capsules_between(points)
    assert np.allclose(start, points[[0, 2, 3]]) and np.allclose(length, [0.3, np.hypot(0.2, 0.1), 0.2])
    directions = np.diff(points, axis=0)[[0, 2, 3]] / length[:, None]
    assert np.allclose(rotate_z(quat), directions, atol=1e-12)          # also the −z segment (a half turn)


def test_track_port_example_runs_logs_and_keeps_its_limits(tmp_path):
    example = load_example("track_port")
    summary = example.main(["--steps", "16", "--settle", "8", "--every", "8", "--out", str(tmp_path)])
    assert set(summary["results"]) == {"whole_body", "decoupled"}
    for r in summary["results"].values():
        assert r["limit_violations"] == 0 and r["steps"] == 16
        assert r["port_max_mm"] <= r["port_radius_mm"]
        assert np.isfinite([r["position_rms_mm"], r["rotation_rms_deg"], r["arm_motion_rad"]]).all()
    path = tmp_path / "track_port.rrd"
    rrd_verify(path)
    data = rrd_data(path)
    for scheme in ("whole_body", "decoupled"):
        for entity in ("arm/links", "arm/frames", "arm/mount", "backbone", "target_path", "tracked_path",
                       "port/port", "port/wall", "tip", "target"):
            assert f"/scene/{scheme}/{entity}" in data, entity
        assert len(data[f"/metrics/position_error_mm/{scheme}"]["Scalars:scalars"]) == 16
    links = data["/scene/whole_body/arm/links"]["Capsules3D:lengths"]
    assert len(links) == 2 and len(links[0]) == 6                  # the Panda's six links of non-zero length
    names = sorted(v["name"] for v in rrd_views(path).values() if v["class"] == "TimeSeries")
    assert names[0].startswith("tip position error [mm]: whole body RMS")


def test_arm_helpers_name_bad_shapes(tmp_path):
    rec = rr.RecordingStream("test_arm_viz")
    rec.set_sinks(rr.FileSink(str(tmp_path / "x.rrd")))
    with pytest.raises(ValueError, match="frames of 'arm'"):
        log_arm(rec, "arm", np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="centre of 'port'"):
        log_port(rec, "port", np.zeros(2), 0.01)
    rec.disconnect()
