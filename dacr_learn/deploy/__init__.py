"""Deploying trained models: folded inference modules, their export, and a controller that uses them.

- :mod:`.inference`               folded FK / Jacobian / IK modules of the monolithic learned models
- :mod:`.inference_compositional` the same for the compositional FK (per-segment transforms and their product)
- :mod:`.export`                  writing, verifying and loading exported modules (``torch.export`` programs,
                                  AOTInductor packages, checked metadata), shared by every model family, and the
                                  exporter of ``train.py`` checkpoints. The command line and the dispatch on a
                                  checkpoint's format: :mod:`dacr_learn.export` (``python -m dacr_learn.export``)
- :mod:`.control`                 resolved-rate (damped least-squares) control in Clarke space

Builds on the maths (:mod:`dacr_learn.models`, :mod:`dacr_learn.compositional`, :mod:`dacr_learn.clarke_space`, the
kinematics); imports no Lightning and no Rerun. The hardware models' counterparts are in
:mod:`dacr_learn.hardware.deploy`, which builds on this package.
"""
