"""Recordings (dacr_learn.hardware.recording): a file that is not UTF-8 gives a ValueError naming it, a missing one a
FileNotFoundError."""
from __future__ import annotations

import re

import pytest
from conftest import names

pytestmark = pytest.mark.usefixtures("one_thread")


def test_recording_that_is_not_utf8_or_missing(tmp_path):
    from dacr_learn.hardware.recording import load_recording

    path = tmp_path / "rec.csv"
    path.write_bytes(b"timestamp,pattern_label\n\xff\xfe,\x00\n")
    with pytest.raises(ValueError, match=names(path, "expected a recording CSV", "UTF-8")):
        load_recording(path)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "missing.csv"))):
        load_recording(tmp_path / "missing.csv")
