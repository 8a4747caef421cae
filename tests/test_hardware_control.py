"""Resolved-rate control in servo space on a hardware model (examples/control_hardware_model.py).

The plant and the Jacobian are the small synthetic hardware model of tests/test_hardware_deploy.py
(a history model: its play state is passed on each step), in memory and exported.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch
from conftest import roundoff_tol
from hardware_testkit import TIP_SCALE, command_recording, synthetic_model

from dacr_learn import export as dexport
from dacr_learn.control import scaled_dls_step
from dacr_learn.hardware.deploy.checkpoint import save_hardware_model
from dacr_learn.hardware.deploy.inference import HardwareFK, HardwareJacobian

pytestmark = pytest.mark.usefixtures("one_thread")
ROOT = Path(__file__).resolve().parents[1]
RETENSION = 0.01                               # the slack pull of the re-tension test (scaled step per control step)


def _example():
    spec = importlib.util.spec_from_file_location("control_hardware_model",
                                                  ROOT / "examples" / "control_hardware_model.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module                     # the example's dataclass looks its module up
    spec.loader.exec_module(module)
    return module


def test_scaled_dls_step_solves_the_task_and_respects_the_step_limit():
    g = torch.Generator().manual_seed(0)
    jac = torch.randn(4, 3, 8, generator=g, dtype=torch.float64)
    task = 1e-3 * torch.randn(4, 3, generator=g, dtype=torch.float64)
    scale = 0.5 + torch.rand(8, generator=g, dtype=torch.float64)
    step = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3)       # undamped, unlimited: J·Δu = Δx
    assert ((jac @ step.unsqueeze(-1)).squeeze(-1) - task).abs().max() <= roundoff_tol(torch.float64, 1e-3, 1024)
    # minimum norm in z = u / s: Δz lies in the row space of J̃ = J·diag(s)
    dz, jt = step / scale, jac * scale
    proj = jt.mT @ torch.linalg.solve(jt @ jt.mT, jt @ dz.unsqueeze(-1))
    assert (proj.squeeze(-1) - dz).abs().max() <= roundoff_tol(torch.float64, float(dz.abs().max()), 1024)
    short = scaled_dls_step(jac, task, scale, damping=1e-2, max_step=1e-5)
    assert torch.allclose(torch.linalg.vector_norm(short / scale, dim=-1), torch.full((4,), 1e-5, dtype=torch.float64))


def test_scaled_dls_step_adds_the_secondary_step_in_the_null_space():
    g = torch.Generator().manual_seed(1)
    jac = torch.randn(3, 8, generator=g, dtype=torch.float64)
    task = 1e-3 * torch.randn(3, generator=g, dtype=torch.float64)
    scale = 0.5 + torch.rand(8, generator=g, dtype=torch.float64)
    z2 = 1e-2 * torch.randn(8, generator=g, dtype=torch.float64)
    plain = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3)
    both = scaled_dls_step(jac, task, scale, damping=0.0, max_step=1e3, secondary=z2)
    tol = roundoff_tol(torch.float64, 1e-2, 1024)
    assert (jac @ both - task).abs().max() <= tol                        # the task is still solved exactly
    jt = jac * scale                                                     # the rest is z₂ minus its row-space part
    null_part = z2 - jt.mT @ torch.linalg.solve(jt @ jt.mT, jt @ z2)
    assert ((both - plain) / scale - null_part).abs().max() <= tol
    assert float(null_part.norm()) > 1e-3                                # not a vacuous check
    zero_column = jac.clone()
    zero_column[:, 2] = 0.0                                              # a slack tendon: J does not see it
    e2 = torch.zeros(8, dtype=torch.float64)
    e2[2] = 1e-2
    step = scaled_dls_step(zero_column, torch.zeros(3, dtype=torch.float64), scale, 1e-3, 1e3, secondary=e2)
    assert torch.allclose(step, e2 * scale, rtol=0, atol=tol)           # passes unchanged, even damped
    with pytest.raises(ValueError, match=r"secondary: expected shape \(8,\)"):
        scaled_dls_step(jac, task, scale, 0.0, 1.0, secondary=torch.zeros(7, dtype=torch.float64))


def test_slack_pull_pulls_in_only_slack_servos():
    example = _example()
    jac = torch.ones(3, 4, dtype=torch.float64)
    jac[:, 1] = 0.0                                                      # servos 1 and 3 slack
    jac[:, 3] = 0.0
    sign = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=torch.float64)     # servo 3 pulls in downwards
    pull = example.slack_pull(jac, sign, 0.01)
    assert torch.equal(pull, torch.tensor([0.0, 0.01, 0.0, -0.01], dtype=torch.float64))
    meta = {"servo_ids": ["b", "a"], "servo_map": {"servos": [{"servo": "a", "sign": -1}, {"servo": "b", "sign": 1}]}}
    assert torch.equal(example.servo_signs(meta), torch.tensor([1.0, -1.0], dtype=torch.float64))
    assert example.ServoControl().retension == 0.0                       # opt-in
    for bad in (-0.1, 0.2):
        with pytest.raises(ValueError, match="retension"):
            example.ServoControl(max_step=0.1, retension=bad)


def test_controller_re_tensions_a_slack_tendon_the_tip_task_cannot():
    """From training command 78 to the tip of command 0 the tip task alone stalls on the history test
    model (the tendons it needs are slack: their columns of J are zero); the null-space pull reaches it."""
    example = _example()
    model = synthetic_model(history=True)
    fk, jac = HardwareFK(model, torch.float64), HardwareJacobian(model, torch.float64)
    commands = 1e3 * command_recording(200, 0).servo
    lower, upper = commands.min(0).values, commands.max(0).values
    goal, start = commands[0], commands[78]
    target = fk(goal[None], fk.initial_state(goal[None]))[0][0].double()
    final = {}
    for retension in (0.0, RETENSION):
        res = example.run_control(fk, jac, target.expand(150, 3), start, fk.initial_state(start[None]), lower,
                                  upper, example.ServoControl(gain=0.5, damping=1e-3, max_step=0.1,
                                                              retension=retension))
        final[retension] = float((torch.from_numpy(res["actual"][-1]) - target).norm())
        servo = torch.from_numpy(res["servo"])
        assert bool(((servo >= lower - 1e-12) & (servo <= upper + 1e-12)).all()), "commands stay in the box"
    assert final[0.0] > 1e-3, final                                      # the stall this second task is for
    assert final[RETENSION] <= 1e-6 * TIP_SCALE, final                   # reached (0.15 µm)


def _task(model):
    """Box of the training-like commands [mm], the start command and a reachable target (the model's tip)."""
    commands = 1e3 * command_recording(200, 0).servo
    lower, upper = commands.min(0).values, commands.max(0).values
    goal, start = commands[37], torch.zeros(commands.shape[1], dtype=torch.float64).clamp(lower, upper)
    return lower, upper, goal, start


def _reach(example, fk, jac, init, lower, upper, goal, start, steps=60):
    target = fk(goal[None], init(goal[None]))[0][0].double()
    res = example.run_control(fk, jac, target.expand(steps, 3), start, init(start[None]), lower, upper,
                              example.ServoControl(gain=0.5, damping=1e-3, max_step=0.1))
    err = (torch.from_numpy(res["actual"]) - target).norm(dim=-1)
    servo = torch.from_numpy(res["servo"])
    assert bool(((servo >= lower - 1e-12) & (servo <= upper + 1e-12)).all()), "commands stay in the box"
    return err


def test_controller_reaches_a_static_target_on_the_history_model():
    example = _example()
    model = synthetic_model(history=True)
    fk, jac = HardwareFK(model, torch.float64), HardwareJacobian(model, torch.float64)
    lower, upper, goal, start = _task(model)
    err = _reach(example, fk, jac, fk.initial_state, lower, upper, goal, start)
    assert float(err[0]) > 1e-3                                                  # a real move (> 1 mm)
    assert float(err[-1]) <= 1e-3 * float(err[0])                                # converged to < 0.1 % of it


def test_controller_runs_the_exported_modules_causally(tmp_path):
    example = _example()
    model = synthetic_model(history=True, members=2)
    dexport.export_checkpoint(save_hardware_model(model, tmp_path / "model.pt"), tmp_path / "export", aoti=False)
    fk, jac, init, meta = example.load_modules(tmp_path / "export")
    assert meta["history"] and init is not None
    lower, upper, goal, start = _task(model)
    err = _reach(example, fk, jac, init, lower, upper, goal, start)
    # float32 modules: converged to float32 rounding at tip scale (the DLS steps are float64)
    assert float(err[-1]) <= max(1e-3 * float(err[0]), roundoff_tol(torch.float32, TIP_SCALE, ulps=4096))
