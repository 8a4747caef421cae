"""The C++ classes of the other module kinds against the Python modules on the same packages (cpp/, docs/cpp.md):
``dacr::HardwareModule`` (a saved hardware model's fk / jacobian / initial_state, the play state fed back),
``dacr::InverseKinematics`` (ik: pose → q) and ``dacr::WholeBodyStep`` (the whole-body control step of an arm
carrying the 3-segment robot, ``python -m dacr_learn.arm.exported``), each called from C++ (``dacr_run``: the batch
call, the class's plain-buffer call row by row, and closed loops) on recorded inputs.

The whole-body step's metadata is checked against the arm's URDF (parsed independently, tests/arm_reference.py) and
the robot file without a compiler. The C++ build is test_cpp's (reused from ``cpp/build``). The AOTInductor packages
take minutes of CPU each on the 2-core machine, so their tests run only when asked: ``DACR_TEST_CPP_MODULES=1``
(IK and hardware packages) and ``DACR_TEST_CPP_ARM=1`` (the whole-body step); ``DACR_TEST_AOTI=0`` skips them all.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
import test_cpp
import torch
from arm_reference import UrdfArm
from conftest import ROOT, save_small_checkpoint
from test_cpp import edit_package, needs_cpp, run_cpp

from dacr_learn import export as dexport
from dacr_learn.arm.control import Port, WholeBodyConfig, WholeBodyController
from dacr_learn.arm.exported import examples, export_control_step, step_metadata
from dacr_learn.checks import F64
from dacr_learn.cli import arm_exported
from dacr_learn.cli.loading import composite_from_files
from dacr_learn.console import run_cli
from dacr_learn.data import generate
from dacr_learn.deploy.package_metadata import PREFIX, joint_names, package_metadata, robot_entries
from dacr_learn.robot import RobotSpec
from dacr_learn.training import IKModule

pytestmark = pytest.mark.usefixtures("one_thread")
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
URDF, TIP, MOUNT = ROOT / "configs" / "arms" / "panda.urdf", "panda_link8", ROOT / "configs/arms/panda_mount.npy"
cpp_build = test_cpp.cpp_build                   # the fixture that builds cpp/ (incremental: reused from cpp/build)
needs_modules = pytest.mark.skipif(os.environ.get("DACR_TEST_CPP_MODULES") != "1",
                                   reason="DACR_TEST_CPP_MODULES=1 builds the IK and hardware packages (minutes)")
needs_arm = pytest.mark.skipif(os.environ.get("DACR_TEST_CPP_ARM") != "1",
                               reason="DACR_TEST_CPP_ARM=1 builds the whole-body step's package (minutes)")


@pytest.fixture(scope="module")
def composite():
    return composite_from_files(URDF, TIP, MOUNT, ROBOT)


def _controller(model) -> WholeBodyController:
    centre = model.base_pose(model.home[None])[0, :3, 3]
    return WholeBodyController(model, WholeBodyConfig(dt=1e-3), Port(tuple(centre.tolist()), 0.005))


def test_whole_body_step_metadata_describes_arm_and_robot(composite):
    """Joint order (the URDF's movable joints root → tip, then the robot's), units, the URDF's limits, the mount,
    the robot's feature entries and the module's shapes, against the files themselves."""
    ctrl = _controller(composite)
    meta = {k.removeprefix(PREFIX): v for k, v in package_metadata(step_metadata(ctrl), "step").items()}
    urdf, spec = UrdfArm(URDF, TIP), RobotSpec.from_yaml(ROBOT)
    robot_names, robot_units = joint_names(spec)
    n = len(urdf.names) + spec.num_joints
    assert meta["module"] == "step" and meta["task"] == "whole_body_control" and meta["dtype"] == "float64"
    assert meta["inputs"] == f"q:{n},target:4x4,feedforward:6" and meta["outputs"] == f"q:{n}"
    assert meta["joint_names"].split(",") == urdf.names + robot_names and int(meta["arm_joints"]) == 7
    assert meta["joint_units"].split(",") == ["rad"] * 7 + robot_units
    assert n == composite.num_joints
    f = lambda key: np.array([float(v) for v in meta[key].split(",")])  # noqa: E731
    np.testing.assert_array_equal(f("arm_lower"), urdf.lower)
    np.testing.assert_array_equal(f("arm_upper"), urdf.upper)
    velocity = [float(j.find("limit").get("velocity")) for j in urdf.movable]
    np.testing.assert_array_equal(f("arm_velocity"), velocity)
    np.testing.assert_array_equal(f("mount").reshape(4, 4), np.load(MOUNT))
    np.testing.assert_array_equal(f("port_centre"), np.array(ctrl.port.centre))
    assert float(meta["port_radius"]) == 0.005 and float(meta["dt"]) == 1e-3 and float(meta["gain"]) == 0.5
    assert float(meta["rotation_length"]) == spec.total_length
    robot = robot_entries(spec)
    assert all(meta[k] == v for k, v in robot.items() if k not in ("joint_names", "joint_units"))


@pytest.mark.slow
def test_arm_exported_cli_writes_a_verified_program(composite, tmp_path):
    """python -m dacr_learn.arm.exported --no-aoti: the torch.export program, loaded back, is the eager controller's
    step in joints (the port at the given point, the period's velocity limits); metadata.json names its sources."""
    centre = [f"{v:.6f}" for v in _controller(composite).port.centre]       # no exponent: -1e-17 reads as a flag
    ctrl = WholeBodyController(composite, WholeBodyConfig(dt=1e-3), Port(tuple(float(v) for v in centre), 0.005))
    meta = arm_exported.main(["--arm", str(URDF), "--arm-tip", TIP, "--mount", str(MOUNT), "--robot", str(ROBOT),
                              "--out", str(tmp_path), "--port", *centre, "--dt", "0.001", "--no-aoti"])
    assert set(meta["sources"]) == {"arm", "mount", "robot"} and meta["task"] == "whole_body_control"
    step = dexport.load(tmp_path, "step")
    assert step.kind == "export"
    q, target, ff = examples(composite, 8, seed=9)
    with torch.no_grad():
        got = step(q, target, ff)
    torch.testing.assert_close(got, ctrl.step(q, target, ff), rtol=0, atol=1e-12)
    assert (got - q).abs().max() > 1e-4


def test_arm_exported_cli_names_a_bad_mount(tmp_path, capsys):
    (tmp_path / "m.npy").write_bytes(b"not numpy")
    args = ["--arm", str(URDF), "--arm-tip", TIP, "--mount", str(tmp_path / "m.npy"), "--robot", str(ROBOT),
            "--out", str(tmp_path / "out"), "--no-aoti"]
    assert run_cli(arm_exported.main, args) == 2
    assert "--mount" in capsys.readouterr().err and not (tmp_path / "out").exists()


def _write(tmp_path, name: str, *arrays: torch.Tensor) -> list:
    files = []
    for i, x in enumerate(arrays):
        files.append(tmp_path / f"{name}{i}.bin")
        x.contiguous().numpy().tofile(files[-1])
    return files


def _cpp_run(build, tmp_path, package, module: str, inputs: tuple[torch.Tensor, ...]) -> tuple[list, list]:
    """``dacr_run run``: (batch outputs in the package's dtype, the class's row-by-row outputs in float64)."""
    b = inputs[0].shape[0]
    run_cpp(build / "dacr_run", "run", package, "--module", module, "--batch", b, "--out", tmp_path / module,
         *_write(tmp_path, module, *inputs))
    loaded = dexport.load(package)
    batch, rows = [], []
    for k, (_, shape) in enumerate(loaded.metadata["modules"][module]["outputs"]):
        dtype = np.float64 if loaded.dtype == torch.float64 else np.float32
        batch.append(np.fromfile(tmp_path / f"{module}.{k}.bin", dtype=dtype).reshape(b, *shape))
        rows.append(np.fromfile(tmp_path / f"{module}.{k}.rows.bin").reshape(b, *shape))
    return batch, rows


def _assert_equal_to_python(build, tmp_path, package, module: str, inputs: tuple[torch.Tensor, ...]):
    """The C++ batch call and the class's plain-buffer calls row by row equal the Python module's calls bit for bit."""
    batch, rows = _cpp_run(build, tmp_path, package, module, inputs)
    loaded = dexport.load(package)
    with torch.no_grad():
        ref = loaded(*inputs)
        ref_rows = [loaded(*(x[b:b + 1] for x in inputs)) for b in range(inputs[0].shape[0])]
    ref = (ref,) if isinstance(ref, torch.Tensor) else ref
    for k, r in enumerate(ref):
        np.testing.assert_array_equal(batch[k], r.numpy())
        by_row = torch.cat([x if isinstance(x, torch.Tensor) else x[k] for x in ref_rows])
        np.testing.assert_array_equal(rows[k], by_row.double().numpy())


@pytest.fixture(scope="module")
def step_package(composite, tmp_path_factory):
    out = tmp_path_factory.mktemp("cpp_step")
    ctrl = _controller(composite)
    export_control_step(composite, out, config=ctrl.config, port=ctrl.port)
    return out / "step.aoti.pt2"


@pytest.mark.slow
@needs_cpp
@needs_arm
def test_whole_body_step_cpp_equals_python(cpp_build, composite, step_package, tmp_path):
    """dacr::WholeBodyStep: the batch call and the plain-buffer call on 16 recorded rows equal the Python module; a
    200-tick closed loop (q fed back) towards a moving target equals the Python loop on the same package bit for bit
    and the eager controller to round-off."""
    q, target, ff = examples(composite, 16, seed=5)
    _assert_equal_to_python(cpp_build, tmp_path, step_package, "step", (q, target, ff))
    ticks, ctrl = 200, _controller(composite)
    t = torch.arange(ticks, dtype=F64)[:, None] * 1e-3
    moving = target[:1].repeat(ticks, 1, 1)
    moving[:, :3, 3] += 0.01 * torch.cat([torch.sin(2 * torch.pi * t), 1 - torch.cos(2 * torch.pi * t), 0 * t], -1)
    feed = torch.cat([torch.diff(moving[:, :3, 3], dim=0, append=moving[-1:, :3, 3]), torch.zeros(ticks, 3,
                                                                                                  dtype=F64)], -1)
    run_cpp(cpp_build / "dacr_run", "loop", step_package, "--steps", ticks, "--out", tmp_path / "loop",
         *_write(tmp_path, "loop", q[:1], moving, feed))
    got = np.fromfile(tmp_path / "loop.0.bin").reshape(ticks, -1)
    loaded, state, ref, eager = dexport.load(step_package), q[:1], [], q[:1]
    with torch.no_grad():
        for k in range(ticks):
            state = loaded(state, moving[k:k + 1], feed[k:k + 1])
            eager = ctrl.step(eager, moving[k:k + 1], feed[k:k + 1])
            ref.append(state)
    np.testing.assert_array_equal(got, torch.cat(ref).numpy())
    np.testing.assert_allclose(got[-1], eager[0].numpy(), rtol=0, atol=1e-9)
    assert np.abs(got[-1] - q[0].numpy()).max() > 1e-3                      # it moved
    run = cpp_build / "dacr_run"
    names = run_cpp(run, "info", step_package).stdout.split("joint_names ")[1].split()[0].split(",")
    swapped = ",".join([names[1], names[0], *names[2:]])
    arm = edit_package(step_package, tmp_path / "a.pt2", lambda m: {**m, PREFIX + "arm_joints": "0"})
    two = edit_package(step_package, tmp_path / "i.pt2", lambda m: {**m, PREFIX + "inputs": "q:19,target:4x4"})
    for args, message in [((step_package, "--joints", swapped), "joint order [panda_joint1,panda_joint2"),
                          ((arm, "--module", "step"), "arm_joints must count 1 … 18 of the joints"),
                          ((two, "--module", "step"), "does not run on inputs of its metadata's shapes")]:
        inputs = _write(tmp_path, "x", q[:1], target[:1], ff[:1])
        out = run_cpp(run, "loop", *args, "--steps", 1, "--out", tmp_path / "x", *inputs, check=False)
        assert out.returncode == 1 and message in out.stderr, (args, out.stderr)


@pytest.fixture(scope="module")
def ik_package(tmp_path_factory):
    """The AOTInductor package of a small IK network of the 3-segment robot (random weights, fitted normalisation)."""
    d = tmp_path_factory.mktemp("cpp_ik")
    torch.manual_seed(0)
    save_small_checkpoint(IKModule(robot=str(ROBOT), width=16, depth=2), d / "ik.ckpt")
    dexport.export_checkpoint(d / "ik.ckpt", d / "ik")
    return d / "ik" / "ik.aoti.pt2"


@pytest.mark.slow
@needs_cpp
@needs_modules
def test_inverse_kinematics_cpp_equals_python(cpp_build, ik_package, tmp_path):
    """dacr::InverseKinematics (ik: pose → q) on 16 recorded poses: C++ batch and plain-buffer calls = Python."""
    pose = generate(RobotSpec.from_yaml(ROBOT), 16, seed=11)["pose"].float()
    _assert_equal_to_python(cpp_build, tmp_path, ik_package, "ik", (pose,))


@pytest.fixture(scope="module")
def hardware_packages(tmp_path_factory):
    """The one-member history test model (hardware_testkit), saved as --save writes it and exported with its three
    AOTInductor packages: (export folder, recorded commands [mm] float32)."""
    from hardware_testkit import saved_history_model

    root = tmp_path_factory.mktemp("cpp_hw")
    _, ckpt, commands = saved_history_model(root, members=1)
    dexport.export_checkpoint(ckpt, root / "export")
    return root / "export", commands.float()


@pytest.mark.slow
@needs_cpp
@needs_modules
def test_hardware_module_cpp_equals_python(cpp_build, hardware_packages, tmp_path):
    """dacr::HardwareModule: initial_state and jacobian on recorded commands and states (batch and row by row), and fk
    in a causal loop of 60 commands with the play state fed back from C++, equal the Python modules bit for bit."""
    out, commands = hardware_packages
    servo = commands[:60]
    init = dexport.load(out, "initial_state")
    fk = dexport.load(out, "fk")
    state, tips, states = init(servo[:1]), [], []
    with torch.no_grad():
        for k in range(servo.shape[0]):
            tip, std, state = fk(servo[k:k + 1], state)
            tips.append(torch.cat([tip, std], -1))
            states.append(state)
    _assert_equal_to_python(cpp_build, tmp_path, out / "initial_state.aoti.pt2", "initial_state", (servo[:16],))
    _assert_equal_to_python(cpp_build, tmp_path, out / "jacobian.aoti.pt2", "jacobian",
                            (servo[1:17], torch.cat(states[:16])))
    start = init(servo[:1]).double()
    run_cpp(cpp_build / "dacr_run", "loop", out / "fk.aoti.pt2", "--steps", 60, "--out", tmp_path / "fk",
         *_write(tmp_path, "fk", servo.double(), start))
    got = [np.fromfile(tmp_path / f"fk.{k}.bin").reshape(60, -1) for k in range(3)]
    np.testing.assert_array_equal(np.concatenate(got[:2], -1), torch.cat(tips).double().numpy())
    np.testing.assert_array_equal(got[2], torch.cat(states).double().reshape(60, -1).numpy())
