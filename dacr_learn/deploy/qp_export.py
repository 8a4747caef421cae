"""The constrained (QP) control step exported: everything up to the solve as one AOTInductor package.

:class:`StepProgram` is a :class:`~.qp_control.QPController`'s step from the joints to its programs' rows
(variables, tip and body evaluation, clearances, task, :meth:`~.qp_control.QPController.program_rows`) as an
``nn.Module``; :func:`export_step` compiles it for one batch size and target kind (minutes; the model, the config
and the scene's obstacles become constants); :class:`ExportedStep` calls the package once per step (its loader
directly, without the per-call argument tree of the package's Python wrapper), solves each program with the
controller (:meth:`~.qp_control.QPController.solve_rows`, DAQP) and returns the joints: the controller's own
step, to the solver's tolerance. Float64; pure Python, no Lightning, no Rerun.
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from ..checks import F64
from .export import inline_products
from .qp_control import QPController, Rows

SHAPES_KEY = "qp_step_shapes"


def step_feedforward(q: Tensor, target: Tensor) -> Tensor:
    """The zero feedforward (B, 6) for pose targets (B, 4, 4), (B, 3) for positions (the exported step takes one;
    zero gives the step without a feedforward)."""
    return q.new_zeros(len(q), 6 if target.dim() == 3 else 3, dtype=F64)


def shapes_text(q: Tensor, target: Tensor, feedforward: Tensor) -> str:
    """The package's shapes as its metadata holds them: "1,9;1,3;1,3" (q, target, feedforward)."""
    return ";".join(",".join(str(n) for n in t.shape) for t in (q, target, feedforward))


class StepProgram(nn.Module):
    """A controller's step up to the solve: joints q (B, N), target (B, 4, 4) or (B, 3) [m], feedforward (B, 6)
    or (B, 3) → (x (B, D), H, g, G, h, lb, ub, kind) (:class:`~.qp_control.Rows`), from the model's own
    evaluation (:meth:`~.qp_control.QPController.evaluate`, not a ``sense`` given)."""

    def __init__(self, controller: QPController):
        super().__init__()
        self.controller = controller

    def forward(self, q: Tensor, target: Tensor, feedforward: Tensor) -> tuple[Tensor, ...]:
        c = self.controller
        x = c.model.variables(q.to(F64))
        s = c.evaluate(x)
        jac, err = c.task(s, target, feedforward)
        return (x, *c.program_rows(x, s, jac, err))


def step_program(controller: QPController, q: Tensor, target: Tensor, feedforward: Tensor
                 ) -> torch.export.ExportedProgram:
    """:class:`StepProgram` exported at these shapes for contiguous inputs (what :class:`ExportedStep` passes; a
    package assumes its example's strides), its matrix products decomposed (:func:`~.export.inline_products`)."""
    examples = tuple(t.contiguous() for t in (q, target, feedforward))
    return inline_products(torch.export.export(StepProgram(controller), examples))


def export_step(controller: QPController, package: str | Path, q: Tensor, target: Tensor,
                feedforward: Tensor | None = None, **inductor_configs) -> Path:
    """Export :class:`StepProgram` at the shapes of q (B, N), target and feedforward (None: zero) and compile it
    with AOTInductor (temporaries on the stack) into ``package`` (.pt2); ``inductor_configs`` adds to its
    configuration. Scenes of primitives only (a mesh's distance does not trace). Returns the package's path."""
    q, target = q.to(F64), target.to(F64)
    ff = step_feedforward(q, target) if feedforward is None else feedforward.to(F64)
    program = step_program(controller, q, target, ff)
    Path(package).parent.mkdir(parents=True, exist_ok=True)
    torch._inductor.aoti_compile_and_package(program, package_path=str(package), inductor_configs={
        "aot_inductor.allow_stack_allocation": True,
        "aot_inductor.metadata": {SHAPES_KEY: shapes_text(q, target, ff)}} | inductor_configs)
    return Path(package)


class ExportedStep:
    """A controller's :meth:`~.qp_control.QPController.step` through a package of :func:`export_step` built from
    the same model, config and scene: ``step(q (B, N), target, feedforward=None)`` → q' (B, N) at the exported
    shapes (ValueError otherwise); ``controller.status`` and ``controller.active`` describe the last step."""

    def __init__(self, controller: QPController, package: str | Path):
        self.controller = controller
        self.loader = torch._inductor.aoti_load_package(str(package)).loader
        text = self.loader.get_metadata().get(SHAPES_KEY)
        if text is None:
            raise ValueError(f"package: expected a QP step package of export_step, got {package}")
        self.shapes = tuple(tuple(int(n) for n in part.split(",") if n) for part in text.split(";"))

    def step(self, q: Tensor, target: Tensor, feedforward: Tensor | None = None) -> Tensor:
        q, target = q.to(F64).contiguous(), target.to(F64).contiguous()
        ff = (step_feedforward(q, target) if feedforward is None else feedforward.to(F64)).contiguous()
        if (q.shape, target.shape, ff.shape) != self.shapes:
            raise ValueError(f"q, target, feedforward: expected the exported shapes {self.shapes}, got "
                             f"{tuple(q.shape), tuple(target.shape), tuple(ff.shape)}")
        x, *rows = self.loader.run([q, target, ff])
        return self.controller.model.joints(self.controller.solve_rows(x, Rows(*rows)))
