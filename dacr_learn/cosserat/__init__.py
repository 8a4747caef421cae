"""Static Cosserat-rod model of tendon-driven continuum robots (docs/cosserat.md): pure physics.

``solve_statics(spec, tension, gravity=..., tip_wrench=..., point_wrenches=...)`` → CosseratSolution
(backbone frames, tip pose, tendon path lengths). Modules: tendon (routing geometry), rod (ODE and
RK4), grid (arc-length nodes), shooting (Newton, implicit gradient), statics (the public solve),
displacement (shapes for given tendon displacements). Datasets sampled from it are in the data layer
(:mod:`dacr_learn.data.cosserat`); nothing here imports the learning code.
"""
from .statics import ConvergenceError, CosseratSolution, solve_statics

__all__ = ["ConvergenceError", "CosseratSolution", "solve_statics"]
