"""dacr_learn.hardware.learned: the play operator (backlash) of the history models; the training steps."""
from __future__ import annotations

import pytest
import torch

from dacr_learn.hardware.learned import STEPS, play_operator, train_full_batch

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


def test_train_full_batch_takes_its_default_steps_from_the_environment(monkeypatch):
    """STEPS steps, or DACR_HARDWARE_STEPS where set (read at each call: a spawned worker inherits it); an explicit
    ``steps`` wins; a value that is no positive whole number is refused naming the variable."""
    w = torch.zeros(1, requires_grad=True)
    calls = []

    def loss():
        calls.append(1)
        return (w - 1).pow(2).sum()

    def steps(**kw):
        calls.clear()
        train_full_batch([w], loss, **kw)
        return len(calls)

    monkeypatch.delenv("DACR_HARDWARE_STEPS", raising=False)
    assert steps() == STEPS
    monkeypatch.setenv("DACR_HARDWARE_STEPS", "7")
    assert steps() == 7 and steps(steps=3) == 3
    for bad in ("0", "-5", "1.5", "many"):
        monkeypatch.setenv("DACR_HARDWARE_STEPS", bad)
        with pytest.raises(ValueError, match=f"DACR_HARDWARE_STEPS='{bad}': expected a positive whole number"):
            train_full_batch([w], loss)
