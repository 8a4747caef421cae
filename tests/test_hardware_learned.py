"""dacr_learn.hardware.learned: the play operator (backlash) of the history models."""
from __future__ import annotations

import pytest
import torch

from dacr_learn.hardware.learned import play_operator

pytestmark = pytest.mark.usefixtures("one_thread")


def test_play_operator_lags_by_the_width():
    v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [1.5, 0.0]], dtype=torch.float64)
    out = play_operator(v, 0.25)
    assert torch.allclose(out[:, 0], torch.tensor([0.0, 0.75, 1.75, 1.75], dtype=torch.float64))
    assert torch.equal(play_operator(v, torch.full((4,), 0.25, dtype=torch.float64)), out)
    per_row = play_operator(v, torch.tensor([0.0, 0.5, 0.1, 0.2], dtype=torch.float64))
    assert torch.allclose(per_row[:, 0], torch.tensor([0.0, 0.5, 1.9, 1.7], dtype=torch.float64))
    x = torch.tensor([[0.0], [1.0], [0.6], [-1.0]], dtype=torch.float64)      # scalar play = clamp
    assert torch.allclose(play_operator(x, 0.3)[:, 0], torch.tensor([0.0, 0.7, 0.7, -0.7], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"broadcastable to \(4,\), got shape \(3,\)"):
        play_operator(v, torch.ones(3, dtype=torch.float64))                  # widths for 3 rows, 4 given
    with pytest.raises(ValueError, match="widths >= 0"):
        play_operator(v, -0.1)
