"""Follow-the-leader planning for a continuum robot, bare or carried by an arm (docs/plan.md).

- :mod:`.path`   the path: a polyline, points at arc lengths, distances to its traversed part
- :mod:`.metric` tip error and shape deviation of a plan (the figures, for any planner's output)
- :mod:`.body`   the robot's backbone and its Jacobian for the planner
- :mod:`.solve`  one step as a least-squares problem (batched), the tip polish
- :mod:`.ftl`    :func:`plan_ftl`: first step, coarse and fine passes, the verdict
"""
from .ftl import FTLOptions, FTLPlan, plan_ftl, robot_length
from .metric import shape_deviation, tip_error
from .path import Path

__all__ = ["FTLOptions", "FTLPlan", "Path", "plan_ftl", "robot_length", "shape_deviation", "tip_error"]
