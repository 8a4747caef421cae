"""Deploying a fitted hardware tip model: save / load it, its uncertainty, inference modules, export.

- :mod:`.checkpoint`  save / load a fitted model (weights-only file; :func:`load_hardware_model`)
- :mod:`.uncertainty` σ per prediction (ensemble spread, σ model) and the out-of-support score
- :mod:`.inference`, :mod:`.compositional_inference`  folded FK / Jacobian modules for export
- :mod:`.generated`   the FK generated from the eager model's own code (the reference of the folded one)
- :mod:`.export`      ``python -m dacr_learn.export --ckpt model.pt``: the exporter of saved hardware models
- :mod:`.control`     resolved-rate control in servo space on an export (examples/control_hardware_model.py)
- :mod:`.ik`          servo commands for a tip position through the IK solver (:mod:`dacr_learn.ik`)

Depends on :mod:`dacr_learn.hardware` (data, physics, models) and :mod:`dacr_learn.deploy`; nothing here imports
the study.
"""
from . import ik  # noqa: F401   (registers HardwareModel with the IK solver)
from .checkpoint import HardwareModel, load_hardware_model, save_hardware_model

__all__ = ["HardwareModel", "load_hardware_model", "save_hardware_model"]
