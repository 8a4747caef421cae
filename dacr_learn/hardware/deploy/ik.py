"""IK of a saved hardware model: servo commands [mm] for a tip position, through the solver of :mod:`dacr_learn.ik`.

>>> from dacr_learn.hardware.deploy import load_hardware_model      # doctest: +SKIP
>>> from dacr_learn.ik import solve_ik
>>> model = load_hardware_model("runs/ftdcr_v4_model/model.pt")
>>> result = solve_ik(model, tip_positions, n_solutions=4, position_only=True)   # result.q: servo commands [mm]
"""
from __future__ import annotations

import torch
from torch import Tensor

from ...body import BodyPoints
from ...checks import F64
from ...ik.adapters import Check, SolverModel, TipJacobian, register_solver_model
from ...limits import Limits
from .checkpoint import HardwareModel
from .inference import HardwareJacobian


class HardwareTip(SolverModel):
    """A saved hardware model (``dacr_learn.hardware.deploy.load_hardware_model``) inverted in servo space.

    Variables are the servo commands [mm] (checkpoint column order) in the box of
    :meth:`~.checkpoint.HardwareModel.servo_range`; the tip is the model's position [m] (position-only IK), its
    Jacobian [m/mm] from the folded inference module (float64); a history model is held static (play state at the
    command). :meth:`check` is the eager ``predict(q, static=True)``, not the folded module the solver iterates with.
    """

    has_rotation = False

    def __init__(self, model):
        self.hardware, self.spec = model, None
        lower, upper = model.servo_range()
        if not bool((upper > lower).all()):
            raise ValueError("ckpt: a servo never moved in the recorded commands; its range is empty")
        self.limits = Limits.boxes(lower, upper, tuple(f"servo {s} [mm]" for s in model.servo_ids))
        self.rest = torch.zeros(len(model.servo_ids), dtype=F64)          # command 0: the rest posture
        self.num_joints = len(model.servo_ids)
        self.length = float(model.spec.total_length)
        self.jacobian_module = HardwareJacobian(model, F64)

    def tip_and_jacobian(self, x: Tensor) -> TipJacobian:
        if not self.hardware.history:
            with torch.no_grad():
                tip, jac = self.jacobian_module(x)
            return TipJacobian(tip, None, jac)
        # A history model held static: the play state follows the command (memory 0 whatever the command), so
        # the Jacobian is that of the static map, not the module's (which holds the state fixed: the effect of
        # the next command given the history). Three reverse-mode passes through the folded FK.
        fk = self.jacobian_module.fk
        servo = x.detach().requires_grad_(True)
        with torch.enable_grad():
            tip = fk(servo, fk.initial_state(servo))[0]
            rows = [torch.autograd.grad(tip[:, i].sum(), servo, retain_graph=i < 2)[0] for i in range(3)]
        return TipJacobian(tip.detach(), None, torch.stack(rows, dim=1))

    def joints(self, x: Tensor) -> Tensor:
        return x

    def variables(self, q: Tensor) -> Tensor:
        return q.to(F64)

    def body(self, x: Tensor, points_per_segment: int = 16) -> BodyPoints:
        """The calibrated physical model's body of servo commands x (B, S) [mm] (motion-capture frame)."""
        return self.hardware.body(x, points_per_segment)

    def check(self, q: Tensor) -> Check:
        tip, _ = self.hardware.predict(q, static=True)
        return Check(tip.to(F64), None, self.limits.inside(q), torch.zeros(q.shape[0], dtype=F64))


register_solver_model(HardwareModel, HardwareTip)
