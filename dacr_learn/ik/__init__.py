"""Inverse kinematics as a solver: every solution, exact and inside the limits, for any model (docs/ik.md).

>>> import torch, dacr_learn as dl
>>> spec = dl.RobotSpec.from_yaml("configs/robots/tdcr_3seg_coupled.yaml")
>>> q_true = dl.ClarkeDecoder(spec)(torch.tensor([[[0.004, 0.0, 0.10, 0.0], [0.0, -0.003, 0.09, 0.0],
...                                                 [0.002, 0.002, 0.08, 0.0]]], dtype=torch.float64))
>>> target = dl.forward_kinematics(spec, dl.ClarkeEncoder(spec)(q_true))          # (1, 4, 4) tip pose [m]
>>> result = dl.solve_ik(spec, target, n_solutions=4)
>>> result.q.shape, bool(result.success.all())
(torch.Size([1, 4, 12]), True)
"""
from ..clarke_space import clarke_limits
from ..limits import Limits
from .adapters import Check, ConstantCurvature, LearnedFK, SolverModel, TipJacobian, as_solver_model
from .refine import levenberg_marquardt
from .solver import IKOptions, IKResult, solve_ik
from .targets import check_targets

__all__ = ["Check", "ConstantCurvature", "IKOptions", "IKResult", "LearnedFK", "Limits", "SolverModel",
           "TipJacobian", "as_solver_model", "check_targets", "clarke_limits", "levenberg_marquardt", "solve_ik"]
