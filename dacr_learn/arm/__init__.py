"""An arm carrying a continuum robot: one differentiable model, whole-body IK and control (docs/arm.md).

- :mod:`.chain`     a URDF arm as a float64 pytorch-kinematics serial chain with its joint limits (:func:`load_arm`)
- :mod:`.composite` :class:`Composite`: arm + mount + any continuum model, FK and closed-form Jacobian; a
  SolverModel, so ``dacr_learn.ik.solve_ik`` inverts it unchanged
"""
from .chain import Arm, load_arm
from .composite import Composite, check_mount, robot_pose

__all__ = ["Arm", "Composite", "check_mount", "load_arm", "robot_pose"]
