"""dacr_learn.hardware.deploy.control: resolved-rate control in servo space on a hardware model, and
examples/control_hardware_model.py, the script that runs it on an export.

The plant and the Jacobian are the small synthetic hardware model of tests/hardware_testkit.py (a history model:
its play state is passed on each step), in memory and exported; the initial command is the IK of the saved model.
"""
from __future__ import annotations

import pytest
import torch
from conftest import load_example, roundoff_tol
from hardware_testkit import IDS, TIP_SCALE, command_recording, saved_history_model, synthetic_model, write_csv

from dacr_learn import export as dexport
from dacr_learn.hardware.deploy import control
from dacr_learn.hardware.deploy.checkpoint import save_hardware_model
from dacr_learn.hardware.deploy.inference import HardwareFK, HardwareJacobian

pytestmark = pytest.mark.usefixtures("one_thread")


RETENSION = 0.01                               # the slack pull of the re-tension test (scaled step per control step)


def test_slack_pull_pulls_in_only_slack_servos():
    jac = torch.ones(3, 4, dtype=torch.float64)
    jac[:, 1] = 0.0                                                      # servos 1 and 3 slack
    jac[:, 3] = 0.0
    sign = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=torch.float64)     # servo 3 pulls in downwards
    pull = control.slack_pull(jac, sign, 0.01)
    assert torch.equal(pull, torch.tensor([0.0, 0.01, 0.0, -0.01], dtype=torch.float64))
    meta = {"servo_ids": ["b", "a"], "servo_map": {"servos": [{"servo": "a", "sign": -1}, {"servo": "b", "sign": 1}]}}
    assert torch.equal(control.servo_signs(meta), torch.tensor([1.0, -1.0], dtype=torch.float64))
    assert control.ServoControl().retension == 0.0                       # opt-in
    for bad in (-0.1, 0.2):
        with pytest.raises(ValueError, match="retension"):
            control.ServoControl(max_step=0.1, retension=bad)


def test_controller_re_tensions_a_slack_tendon_the_tip_task_cannot():
    """From training command 78 to the tip of command 0 the tip task alone stalls on the history test
    model (the tendons it needs are slack: their columns of J are zero); the null-space pull reaches it."""
    model = synthetic_model(history=True)
    fk, jac = HardwareFK(model, torch.float64), HardwareJacobian(model, torch.float64)
    commands = 1e3 * command_recording(200, 0).servo
    lower, upper = commands.min(0).values, commands.max(0).values
    goal, start = commands[0], commands[78]
    target = fk(goal[None], fk.initial_state(goal[None]))[0][0].double()
    final = {}
    for retension in (0.0, RETENSION):
        res = control.run_control(fk, jac, target.expand(150, 3), start, fk.initial_state(start[None]), lower,
                                  upper, control.ServoControl(gain=0.5, damping=1e-3, max_step=0.1,
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


def _reach(fk, jac, init, lower, upper, goal, start, steps=60):
    target = fk(goal[None], init(goal[None]))[0][0].double()
    res = control.run_control(fk, jac, target.expand(steps, 3), start, init(start[None]), lower, upper,
                              control.ServoControl(gain=0.5, damping=1e-3, max_step=0.1))
    err = (torch.from_numpy(res["actual"]) - target).norm(dim=-1)
    servo = torch.from_numpy(res["servo"])
    assert bool(((servo >= lower - 1e-12) & (servo <= upper + 1e-12)).all()), "commands stay in the box"
    return err


def test_controller_reaches_a_static_target_on_the_history_model():
    model = synthetic_model(history=True)
    fk, jac = HardwareFK(model, torch.float64), HardwareJacobian(model, torch.float64)
    lower, upper, goal, start = _task(model)
    err = _reach(fk, jac, fk.initial_state, lower, upper, goal, start)
    assert float(err[0]) > 1e-3                                                  # a real move (> 1 mm)
    assert float(err[-1]) <= 1e-3 * float(err[0])                                # converged to < 0.1 % of it


def test_controller_runs_the_exported_modules_causally(history_export):
    model, _, export, *_ = history_export
    fk, jac, init, meta = control.load_hardware_export(export)
    assert meta["history"] and init is not None
    lower, upper, goal, start = _task(model)
    err = _reach(fk, jac, init, lower, upper, goal, start)
    # float32 modules: converged to float32 rounding at tip scale (the DLS steps are float64)
    assert float(err[-1]) <= max(1e-3 * float(err[0]), roundoff_tol(torch.float32, TIP_SCALE, ulps=4096))


def test_the_initial_command_reaches_the_target_inside_the_recorded_range(tmp_path):
    """initial_command: IK of the saved model; checked through the folded float64 FK module with the play state
    started at the command (independent of the eager ensemble the solver's verdict uses)."""
    model, _, commands = saved_history_model(tmp_path)
    fk = HardwareFK(model, torch.float64)
    lower, upper = model.servo_range()
    rest = torch.zeros(len(IDS), dtype=torch.float64)
    for row in (37, 120):
        goal = commands[row]
        target = fk(goal[None], fk.initial_state(goal[None]))[0][0].double()       # reachable by construction
        u0, err = control.initial_command(model, target, rest)
        assert u0.shape == (len(IDS),) and bool(((u0 >= lower) & (u0 <= upper)).all()), "inside the recorded range"
        reached = fk(u0[None], fk.initial_state(u0[None]))[0][0]
        assert float((reached - target).norm()) <= 1e-6 + roundoff_tol(torch.float64, TIP_SCALE)   # IK tolerance
        assert err <= 1e-6 and float((u0 - rest).abs().max()) > 0.1                 # a real move from rest [mm]
        near, _ = control.initial_command(model, target, goal)                     # warm start on an exact answer
        assert float((near - goal).abs().max()) <= 1e-3, "the solution nearest the current command comes first"
    far = fk(rest[None], fk.initial_state(rest[None]))[0][0].double() + torch.tensor([0.0, 0.0, 0.5],
                                                                                       dtype=torch.float64)
    with pytest.raises(ValueError, match="no command in the recorded servo range reaches it"):
        control.initial_command(model, far, rest)
    with pytest.raises(ValueError, match="target \\(3,\\) \\[m\\] and current \\(8,\\)"):
        control.initial_command(model, far[:2], rest)


def test_the_example_script_tracks_a_circle_on_an_export(history_export, tmp_path, capsys):
    model, path, export, _, commands, _ = history_export
    train = write_csv(tmp_path / "train.csv", ["timestamp", "pattern_label", *(f"servo_{i}_mm" for i in IDS),
                                               "tip_x", "tip_y", "tip_z"],
                      [[k, "p", *row, 0.0, 0.0, 0.0] for k, row in enumerate(commands.tolist())])
    example = load_example("control_hardware_model")
    summary = example.main(["--export", str(export), "--train", str(train), "--radius", "0.5",
                            "--drop", "0", "--period", "100", "--laps", "1", "--settle", "40", "--hold", "40",
                            "--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / "summary.json").is_file() and "THE PLANT IS THE LEARNED MODEL" in capsys.readouterr().out
    start = summary["initial_command"]                                        # the IK's command for the first point
    u0 = torch.tensor(start["servo_mm"], dtype=torch.float64)
    assert bool(((u0 >= commands.amin(0)) & (u0 <= commands.amax(0))).all()) and start["ik_error_mm"] <= 1e-3
    assert start["export_error_mm"] <= 1e3 * roundoff_tol(torch.float32, TIP_SCALE, ulps=4096)   # float32 modules
    circle = summary["results"]["circle"]
    assert circle["steps"] == 100 and circle["rms_mm"] < 0.05                      # a 0.5 mm circle, tracked
    statics = [r for name, r in summary["results"].items() if name.startswith("static")]
    assert len(statics) == 4 and all(r["final_error_mm"] < r["start_error_mm"] for r in statics)
    # --ckpt of another model is refused by the function main passes it to (after loading the export: seconds)
    other = save_hardware_model(synthetic_model(history=True, members=1), tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not the checkpoint .* was exported from"):
        example.source_model(export, dexport.read_metadata(export), other)
