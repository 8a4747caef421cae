"""The model-selection study on hardware recordings: ``python -m dacr_learn.hardware`` (its command line:
:mod:`dacr_learn.cli.hardware`).

- :mod:`.registry`   the tip models: name → builder and flags
- :mod:`.selection`  train-only selection proxies (family CV, singles → pairs) and the default model
- :mod:`.benchmark`  calibrate, fit, score, train, evaluate on a train (+ optional val) recording
- :mod:`.heldout`    held-out predictions on the train-only folds and the σ model fitted to them
- :mod:`.pool`       the worker pool the fits run in
- :mod:`.visual`     PNG and Rerun recording of predicted vs measured tip paths

Depends on :mod:`dacr_learn.hardware` and :mod:`dacr_learn.hardware.deploy`; nothing below imports it.
"""
