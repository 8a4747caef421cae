"""Rerun visualisation: what a person sees of a run, a controller or a robot (docs/rerun.md). No maths here.

- :mod:`.logger`   RerunLogger, the Lightning logger of train.py (metrics, the run's blueprint, ``rerun.rrd``)
- :mod:`.callback` RerunVisualCallback: the 3D scene of fixed validation samples every logged epoch
- :mod:`.layout`   blueprints and metric groups (no Lightning)
- :mod:`.scene`    3D scene helpers: backbones, tip frames, workspace error colours (no Lightning)

Depends on the maths below it only for data it is handed (tensors); nothing of the maths, data, deploy or
hardware layers imports it, except the hardware study's visuals.
"""
