"""Learning and evaluating tip models on recorded tendon-robot data (docs/hardware.md).

Three layers, each importing only those before it (tests/test_structure.py):

``dacr_learn.hardware`` — data, physics, models:

- :mod:`.recording`   CSV recordings (servo commands + motion-capture tip) → SI tensors, with checks
- :mod:`.servo_map`   servo column → (segment, joint), sign, zero; YAML I/O
- :mod:`.slack`       slack-aware Clarke encoder (tendons as one-sided springs)
- :mod:`.calibration` servo map and joint offsets from single-tendon pulls; :mod:`.calibrate` its CLI
- :mod:`.ccmodel`     calibrated constant-curvature model with a handful of physical parameters (variants:
                      lateral marker, pretension ∝ tendon length)
- :mod:`.learned`     baselines, Clarke-feature networks, CC residuals, synthetic pre-training
- :mod:`.compositional_model`  CC segment transforms × learned per-segment corrections
- :mod:`.cosserat_model`, :mod:`.cosserat_learned`  the calibrated Cosserat rod and the models built on it
- :mod:`.metrics`     offset-removed tip RMSE (the lab's metric), mean and p95 error

:mod:`.deploy` — a fitted model in use: save / load it (``checkpoint``), its σ (``uncertainty``), folded and
generated FK / Jacobian modules (``inference``, ``compositional_inference``, ``generated``), its exporter
(``export``, reached through ``python -m dacr_learn.export``) and servo-space control (``control``).

:mod:`.study` — the model-selection study: registry, train-only selection, benchmark, held-out σ, visuals and
the CLI ``python -m dacr_learn.hardware``.
"""
from .calibration import calibrate
from .ccmodel import CalibratedCC, fit_cc
from .metrics import offset_removed_rmse, tip_metrics
from .recording import Recording, load_recording
from .servo_map import ServoAssignment, ServoMap
from .slack import SlackAwareEncoder

__all__ = ["CalibratedCC", "Recording", "ServoAssignment", "ServoMap", "SlackAwareEncoder", "calibrate",
           "fit_cc", "load_recording", "offset_removed_rmse", "tip_metrics"]
