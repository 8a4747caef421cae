"""dacr_learn.viz.scene: workspace error colours on a fixed log scale, the workspace point cloud thinned."""
from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from rerun_testkit import rrd_chunks, rrd_column

from dacr_learn.viz.scene import DEFAULT_ERROR_RANGE, error_colours, log_workspace


def test_workspace_colours_use_a_fixed_log_scale(tmp_path):
    lo, hi = DEFAULT_ERROR_RANGE
    errors = np.array([lo / 10, lo, 1e-4, hi, hi * 10])
    colours = error_colours(errors, DEFAULT_ERROR_RANGE)
    assert colours.shape == (5, 3) and colours.dtype == np.uint8
    assert (colours[0] == colours[1]).all() and (colours[3] == colours[4]).all()  # clipped at the ends
    # a colour depends on its own error only, not on the others (no per-frame rescaling)
    assert (error_colours(errors[2:3], DEFAULT_ERROR_RANGE) == colours[2]).all()
    assert np.abs(colours[3].astype(int) - colours[1]).sum() > 200  # the two ends differ clearly
    with pytest.raises(ValueError, match="error_range"):
        error_colours(errors, (1e-3, 1e-4))
    path = tmp_path / "ws.rrd"
    rec = rr.RecordingStream("dacr_learn_test")
    rec.set_sinks(rr.FileSink(path))
    pts = np.random.default_rng(0).random((1001, 3)) * 0.1
    max_err = log_workspace(rec, "ws", pts, np.linspace(0, 2e-3, 1001), max_points=100)
    rec.disconnect()
    assert max_err == pytest.approx(2e-3)
    shown = rrd_column(rrd_chunks(path)["/ws"], "Points3D:positions")[0]
    assert 90 <= len(shown) <= 100
