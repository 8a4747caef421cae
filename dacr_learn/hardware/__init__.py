"""Learning and evaluating tip models on recorded tendon-robot data (docs/hardware.md).

Three layers, each importing only those before it (tests/test_structure.py; modules: docs/design.md §5):
``dacr_learn.hardware`` (recordings, servo map, slack-aware encoder, calibration, the calibrated CC and
Cosserat models, the tip models, metrics), :mod:`.deploy` (a fitted model in use: save / load, σ, inference
modules, export, IK, control) and :mod:`.study` (the model-selection study, ``python -m dacr_learn.hardware``).
"""
from .calibration import calibrate
from .ccmodel import CalibratedCC, fit_cc
from .metrics import offset_removed_rmse, tip_metrics
from .recording import Recording, load_recording
from .servo_map import ServoAssignment, ServoMap
from .slack import SlackAwareEncoder

__all__ = ["CalibratedCC", "Recording", "ServoAssignment", "ServoMap", "SlackAwareEncoder", "calibrate",
           "fit_cc", "load_recording", "offset_removed_rmse", "tip_metrics"]
