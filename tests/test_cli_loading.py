"""What the command lines read (dacr_learn.cli.loading): a model file is recognised by its contents, not its name
(read_model_file, shared by ``python -m dacr_learn.ik --ckpt`` and ``python -m dacr_learn.export``), and a file
that is neither kind is a ValueError naming it."""
from __future__ import annotations

import shutil

import pytest
import torch
from conftest import ROOT

from dacr_learn.cli.loading import load_solver_model
from dacr_learn.hardware.deploy import HardwareModel
from dacr_learn.hardware.deploy.checkpoint import read_model_file
from dacr_learn.runs import CHECKPOINT

FIXTURES = ROOT / "tests" / "data" / "main_87f426b"     # tiny trained models (read only)


@pytest.fixture
def renamed(tmp_path):
    """The hardware model saved as ``hw.ckpt`` and the FK checkpoint as ``fk.pt``: names that mislead."""
    shutil.copy(FIXTURES / "hardware_model.pt", tmp_path / "hw.ckpt")
    shutil.copy(FIXTURES / "fk.ckpt", tmp_path / "fk.pt")
    return tmp_path


def test_a_model_file_is_recognised_by_its_contents(renamed):
    hw, fk = read_model_file(renamed / "hw.ckpt"), read_model_file(renamed / "fk.pt")
    assert hw.hardware and hw.path == renamed / "hw.ckpt" and hw.blob["format"].startswith("dacr_learn.hardware")
    assert not fk.hardware and "state_dict" in fk.blob
    model, seeder, description = load_solver_model(None, str(renamed / "hw.ckpt"))
    assert isinstance(model, HardwareModel) and seeder is None and "hardware model" in description
    net, seeder, description = load_solver_model(None, str(renamed / "fk.pt"))
    assert net.task == "fk" and next(net.parameters()).dtype == torch.float64 and seeder is None
    assert "learned FK" in description
    _, seeder, _ = load_solver_model(None, str(FIXTURES / "ik.ckpt"))            # an IK network seeds the solver
    assert seeder is not None


def test_a_file_of_neither_kind_names_itself_and_what_was_expected(tmp_path):
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt: expected") as err:
        load_solver_model(None, str(tmp_path / "other.pt"))
    assert CHECKPOINT in str(err.value)
    with pytest.raises(FileNotFoundError, match="nothere"):
        read_model_file(tmp_path / "nothere.pt")
