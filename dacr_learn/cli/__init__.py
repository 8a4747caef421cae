"""The command lines, above the library: each module has ``main(argv: list[str] | None = None)``, run by the
thin ``__main__`` of the package a user names (``python -m dacr_learn.<package>`` through
:func:`dacr_learn.console.run_cli`: a user error is one ``error: …`` line and exit status 2).

- :mod:`.ik`           ``python -m dacr_learn.ik``: IK for a file of targets (a robot file, a checkpoint, an arm)
- :mod:`.ik_exported`  ``python -m dacr_learn.ik.exported``: export the warm-started IK refinement
- :mod:`.arm_exported` ``python -m dacr_learn.arm.exported``: export the whole-body control step
- :mod:`.export`       ``python -m dacr_learn.export``: export a checkpoint of any format
- :mod:`.hardware`     ``python -m dacr_learn.hardware``: the model-selection study on hardware recordings
- :mod:`.ablation`     ``python -m dacr_learn.ablation``: the Clarke-vs-raw ablation grid
- :mod:`.loading`      what they read: .npy arrays, a model recognised by its file's contents, the arm files
- :mod:`.plan`         ``python -m dacr_learn.plan ftl``: follow-the-leader insertion along a path

Nothing in the library imports this package.
"""
