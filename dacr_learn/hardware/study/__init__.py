"""The model-selection study on hardware recordings: ``python -m dacr_learn.hardware`` (its command line:
:mod:`dacr_learn.cli.hardware`): the model registry, train-only selection, the benchmark, held-out σ, the
worker pool and the figures. Depends on :mod:`dacr_learn.hardware` and :mod:`dacr_learn.hardware.deploy`;
nothing below imports it.
"""
