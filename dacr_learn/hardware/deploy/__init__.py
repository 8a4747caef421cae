"""Deploying a fitted hardware tip model: save / load it (:mod:`.checkpoint`), its uncertainty, folded
inference modules, the exporter (``python -m dacr_learn.export --ckpt model.pt``), IK through
:mod:`dacr_learn.ik` and resolved-rate control. Depends on :mod:`dacr_learn.hardware` and
:mod:`dacr_learn.deploy`; nothing here imports the study.
"""
from . import ik  # noqa: F401   (registers HardwareModel with the IK solver)
from .checkpoint import HardwareModel, load_hardware_model, save_hardware_model

__all__ = ["HardwareModel", "load_hardware_model", "save_hardware_model"]
