"""Learning and evaluating tip models on recorded tendon-robot data (docs/hardware.md).

- :mod:`.recording`   CSV recordings (servo commands + motion-capture tip) → SI tensors, with checks
- :mod:`.servo_map`   servo column → (segment, joint), sign, zero; YAML I/O
- :mod:`.slack`       slack-aware Clarke encoder (tendons as one-sided springs)
- :mod:`.calibration` servo map and joint offsets from single-tendon pulls (also a CLI)
- :mod:`.ccmodel`     calibrated constant-curvature model with a handful of physical parameters (variants:
                      lateral marker, pretension ∝ tendon length)
- :mod:`.learned`     baselines, Clarke-feature networks, CC residuals, synthetic pre-training
- :mod:`.registry`    the model registry: name → builder, flags
- :mod:`.selection`   train-only selection proxies (family CV, singles → pairs) and the default model
- :mod:`.metrics`     offset-removed tip RMSE (the lab's metric), mean and p95 error
- :mod:`.benchmark`   all of the above on a train (+ optional val) recording; ``python -m dacr_learn.hardware``
- :mod:`.compositional_model`  CC segment transforms × learned per-segment corrections (model j)
- :mod:`.visual`      PNG and Rerun recording of predicted vs measured tip paths
- :mod:`.checkpoint`  save / load a fitted default model (weights-only); :mod:`.heldout`, :mod:`.uncertainty`: its σ
- :mod:`.inference`, :mod:`.compositional_inference`, :mod:`.export`  exportable FK / Jacobian modules
"""
from .calibration import calibrate
from .ccmodel import CalibratedCC, fit_cc
from .metrics import offset_removed_rmse, tip_metrics
from .recording import Recording, load_recording
from .servo_map import ServoAssignment, ServoMap
from .slack import SlackAwareEncoder

__all__ = ["CalibratedCC", "Recording", "ServoAssignment", "ServoMap", "SlackAwareEncoder", "calibrate",
           "fit_cc", "load_recording", "offset_removed_rmse", "tip_metrics"]
