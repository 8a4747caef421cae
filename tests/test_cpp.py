"""The C++ library (cpp/, docs/cpp.md) against the Python side: the metadata the packages carry, and the same
AOTInductor packages called from C++ and from Python on the same recorded inputs.

The C++ build (``cpp/build.sh``: cmake + the libtorch of the installed wheel) goes into ``cpp/build`` (the folder of
``make cpp``; ``DACR_CPP_BUILD`` overrides it) and is incremental, so only the first run on a clone compiles (about
1 min of CPU). The Jacobian package (conftest's jacobian_aoti_package, one AOTInductor build shared with
test_export.py) is exported in the session, so the C++ tests are marked slow;
``DACR_TEST_AOTI=0`` skips them, as the other AOTInductor builds. The IK refinement's package takes several minutes of
CPU to build (a one-iteration, position-only one: over 4 min on the 2-core machine), so its tests run only with
``DACR_TEST_CPP_REFINE=1``. Without cmake or a C++ compiler the C++ tests are skipped (AOTInductor needs the compiler
as well).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT

from dacr_learn import export as dexport
from dacr_learn.clarke_space import ClarkeSpace
from dacr_learn.data import generate
from dacr_learn.deploy.control import ControllerConfig, ResolvedRateController
from dacr_learn.deploy.package_metadata import PREFIX, package_metadata
from dacr_learn.ik.exported import export_refinement
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
TYPE3 = ROOT / "configs" / "robots" / "type3.yaml"
needs_cpp = pytest.mark.skipif(shutil.which("cmake") is None or shutil.which("c++") is None
                               or os.environ.get("DACR_TEST_AOTI") == "0",
                               reason="needs cmake and a C++ compiler (DACR_TEST_AOTI=0 skips the AOTInductor builds)")


def _meta(spec: RobotSpec, task: str = "fk") -> dict:
    n, d = spec.num_joints, spec.num_actuated_features
    return {"format": dexport.FORMAT, "task": task, "dtype": "float32", "robot": spec.to_dict(),
            "torch_version": torch.__version__,
            "modules": {"jacobian": {"inputs": [["q", [n]]], "outputs": [["pose", [4, 4]], ["J_f", [6, d]],
                                                                          ["J_q", [6, n]]]}}}


def _floats(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split(",")])


@pytest.mark.parametrize("robot", [ROBOT, TYPE3])
def test_package_metadata_describes_the_robot(robot):
    """Joint order and units, feature limits, and the affine Clarke maps reproduce ClarkeSpace (float64)."""
    spec = RobotSpec.from_yaml(robot)
    meta = {k.removeprefix(PREFIX): v for k, v in package_metadata(_meta(spec), "jacobian").items()}
    assert meta["module"] == "jacobian" and meta["inputs"] == f"q:{spec.num_joints}"
    assert meta["outputs"] == f"pose:4x4,J_f:6x{spec.num_actuated_features},J_q:6x{spec.num_joints}"
    names, units = meta["joint_names"].split(","), meta["joint_units"].split(",")
    assert len(names) == len(units) == spec.num_joints and len(set(names)) == spec.num_joints
    assert units.count("rad") == sum(s.twists for s in spec.segments)
    space = ClarkeSpace(spec)
    f = space.features(generate(spec, 32, seed=3, dtype=torch.float64)["q"]).numpy()
    lower, upper = _floats(meta["feature_lower"]), _floats(meta["feature_upper"])
    disks = np.array([[int(i) for i in p.split()] for p in meta["feature_disks"].split(",")])
    radius = _floats(meta["feature_disk_radius"])
    assert ((f >= lower - 1e-12) & (f <= upper + 1e-12)).all()
    assert (np.hypot(f[:, disks[:, 0]], f[:, disks[:, 1]]) <= radius * (1 + 1e-9)).all()
    assert float(meta["robot_length"]) == spec.total_length
    if not space.linear:                                # type III twists: no affine maps
        assert "decoder_matrix" not in meta
        return
    n, d = spec.num_joints, spec.num_actuated_features
    dec, enc = _floats(meta["decoder_matrix"]).reshape(n, d), _floats(meta["encoder_matrix"]).reshape(d, n)
    q = f @ dec.T + _floats(meta["decoder_offset"])
    np.testing.assert_allclose(q, space.joints(torch.from_numpy(f)).numpy(), atol=1e-15)
    np.testing.assert_allclose(q @ enc.T + _floats(meta["encoder_offset"]), f, atol=1e-14)


def test_package_metadata_of_a_hardware_model_names_its_servos():
    spec = RobotSpec.from_yaml(ROBOT)
    meta = {**_meta(spec, "hardware_fk"), "servo_ids": [7, 3, 5], "history": True}
    meta["modules"] = {"fk": {"inputs": [["servo", [3]], ["state", [3, 2]]],
                              "outputs": [["tip", [3]], ["tip_std", [3]], ["state", [3, 2]]]}}
    got = package_metadata(meta, "fk")
    assert got[PREFIX + "joint_names"] == "servo7,servo3,servo5" and got[PREFIX + "joint_units"] == "mm,mm,mm"
    assert got[PREFIX + "inputs"] == "servo:3,state:3x2" and got[PREFIX + "history"] == "true"
    assert not any("feature" in k for k in got)


def run_cpp(*args, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([str(a) for a in args], capture_output=True, text=True, env=env, timeout=600)
    if check and out.returncode != 0:
        raise AssertionError(f"{args[0]} failed: {out.stderr.strip()}")
    return out


@pytest.fixture(scope="module")
def cpp_build() -> Path:
    build = Path(os.environ.get("DACR_CPP_BUILD", ROOT / "cpp" / "build"))
    env = {**os.environ, "PYTHON": sys.executable, "DACR_CPP_BUILD": str(build)}
    out = subprocess.run(["bash", str(ROOT / "cpp" / "build.sh")], capture_output=True, text=True, env=env,
                         timeout=1800)
    assert out.returncode == 0, out.stderr[-3000:]
    return build


needs_refine = pytest.mark.skipif(os.environ.get("DACR_TEST_CPP_REFINE") != "1",
                                  reason="DACR_TEST_CPP_REFINE=1 builds the refinement's package (minutes)")


@pytest.fixture(scope="module")
def packages(jacobian_aoti_package) -> dict[str, Path]:
    """The AOTInductor package of the jacobian of a small FK model of the 3-segment robot (conftest's
    jacobian_aoti_package: random weights, fitted normalisation; its fk only as a torch.export program)."""
    return {"fk": jacobian_aoti_package}


@pytest.fixture(scope="module")
def refine_package(tmp_path_factory) -> Path:
    """A one-iteration, position-only IK refinement of the 3-segment robot (the smallest refinement graph)."""
    d = tmp_path_factory.mktemp("cpp_refine")
    export_refinement(ROBOT, d, iterations=1, position_only=True)
    return d


def _inputs(name: str, n: int) -> tuple[torch.Tensor, ...]:
    spec = RobotSpec.from_yaml(ROBOT)
    data = generate(spec, n, seed=11, dtype=torch.float64)
    if name != "refine":
        return (data["q"].float(),)
    near = generate(spec, n, seed=12, dtype=torch.float64)["q"]
    return data["pose"][:, :3, 3].contiguous(), data["q"] + 0.05 * (near - data["q"])   # warm starts near the solutions


@pytest.mark.slow
@needs_cpp
@pytest.mark.parametrize("name", ["jacobian", pytest.param("refine", marks=needs_refine)])
def test_cpp_equals_python(cpp_build, request, tmp_path, name):
    """The same package on the same inputs: the C++ batch call and the plain-buffer call row by row equal the Python
    calls (batch and row by row) bit for bit."""
    fixture = request.getfixturevalue
    folder = fixture("refine_package") if name == "refine" else fixture("packages")["fk"]
    inputs = _inputs(name, 16)
    files = []
    for i, x in enumerate(inputs):
        files.append(tmp_path / f"in{i}.bin")
        x.numpy().tofile(files[-1])
    run_cpp(cpp_build / "dacr_run", "run", folder / f"{name}.aoti.pt2", "--module", name, "--batch", 16,
         "--out", tmp_path / "out", *files)
    module = dexport.load(folder, name)
    assert module.kind == "aoti"
    with torch.no_grad():
        batch = module(*inputs)
        rows = [module(*(x[b:b + 1] for x in inputs)) for b in range(16)]
    batch = (batch,) if isinstance(batch, torch.Tensor) else batch
    for k, ref in enumerate(batch):
        got = np.fromfile(tmp_path / f"out.{k}.bin", dtype=ref.numpy().dtype).reshape(ref.shape)
        np.testing.assert_array_equal(got, ref.numpy())
        got_rows = np.fromfile(tmp_path / f"out.{k}.rows.bin", dtype=np.float64).reshape(ref.shape)
        ref_rows = torch.cat([r if isinstance(r, torch.Tensor) else r[k] for r in rows])
        np.testing.assert_array_equal(got_rows, ref_rows.double().numpy())


@pytest.mark.slow
@needs_cpp
def test_cpp_resolved_rate_equals_python(cpp_build, packages, tmp_path):
    """The C++ ResolvedRateController on the exported Jacobian follows the Python one (float64 control maths, the
    same package): 300 ticks towards moving targets, limits active at times."""
    spec = RobotSpec.from_yaml(ROBOT)
    jac = dexport.load(packages["fk"], "jacobian")
    ctrl = ResolvedRateController(spec, jac, ControllerConfig())
    q = generate(spec, 1, seed=5, dtype=torch.float64)["q"]
    with torch.no_grad():
        start = jac(q)[0][0, :3, 3]
    t = torch.arange(300, dtype=torch.float64).unsqueeze(-1) * 2e-3
    circle = torch.cat([torch.cos(t) - 1, torch.sin(t), 0 * t], -1) * 0.02 + start
    targets = torch.cat([circle, torch.diff(circle, dim=0, append=circle[-1:])], -1)
    q.numpy().tofile(tmp_path / "q0.bin")
    targets.numpy().tofile(tmp_path / "targets.bin")
    run_cpp(cpp_build / "dacr_run", "rrc", packages["fk"] / "jacobian.aoti.pt2", "--steps", 300, "--out",
         tmp_path / "q.bin", tmp_path / "q0.bin", tmp_path / "targets.bin")
    got = np.fromfile(tmp_path / "q.bin").reshape(300, -1)
    ref = []
    with torch.no_grad():
        for k in range(300):
            q = ctrl.step(q, targets[k:k + 1, :3], feedforward=targets[k:k + 1, 3:])
            ref.append(q[0].numpy())
    # float64 maths in a different order (Cholesky vs LU, affine encoder vs least squares): rounding at 1e-16 m can
    # flip a float32 rounding of the Jacobian's input, a relative 6e-8 change of one tick's J
    np.testing.assert_allclose(got, np.stack(ref), rtol=0, atol=1e-9)


def edit_package(src: Path, dst: Path, edit) -> Path:
    """A copy of a package with its metadata map changed by ``edit`` (the metadata JSON files inside the zip)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename.endswith("_metadata.json"):
                data = json.dumps(edit(json.loads(data))).encode()
            zout.writestr(item, data)
    return dst


@pytest.mark.slow
@needs_cpp
def test_cpp_refuses_mismatches(cpp_build, packages, tmp_path):
    """A clear one-line error naming the package and what differs: module kind, robot, joint order, format, torch
    version, a package without dacr_learn metadata, a file that is not a package."""
    run = cpp_build / "dacr_run"
    fk = packages["fk"] / "jacobian.aoti.pt2"
    names = run_cpp(run, "info", fk).stdout.split("joint_names ")[1].split()[0].split(",")
    assert names[0] == "s0.q0" and len(names) == 12
    bad = "pose:4x3,J_f:6x9,J_q:6x12"
    cases = [((fk, "--module", "fk"), "module 'jacobian', expected 'fk'"),
             ((fk, "--robot", "other"), "exported for robot 'tdcr-3seg', expected 'other'"),
             ((fk, "--joints", ",".join(names[::-1])), "joint order [s0.q0"),
             ((edit_package(fk, tmp_path / "v.pt2", lambda m: {**m, PREFIX + "torch_version": "2.0.0"}),),
              "built with torch 2.0.0"),
             ((edit_package(fk, tmp_path / "f.pt2", lambda m: {**m, PREFIX + "format": "x/9"}),), "format 'x/9'"),
             ((edit_package(fk, tmp_path / "n.pt2", lambda m: {k: v for k, v in m.items() if PREFIX not in k}),),
              "no dacr_learn metadata in the package"),
             ((edit_package(fk, tmp_path / "s.pt2", lambda m: {**m, PREFIX + "outputs": bad}),),
              "output pose has shape (1, 4, 4), its metadata says (1, 4, 3)"),
             ((packages["fk"] / "metadata.json",), "not an AOTInductor package")]
    for args, message in cases:
        out = run_cpp(run, "info", *args, check=False)
        assert out.returncode == 1 and message in out.stderr and out.stderr.count("\n") == 1, (args, out.stderr)


@pytest.mark.slow
@needs_cpp
def test_resolved_rate_loop_runs(cpp_build, packages):
    """The example's 1 kHz resolved-rate loop runs for 0.2 s and reports its figures; no timing is asserted."""
    rrc = json.loads(run_cpp(cpp_build / "dacr_rt", "rrc", "--jacobian", packages["fk"] / "jacobian.aoti.pt2",
                          "--seconds", 0.2, "--cpu", 0).stdout)
    assert rrc["ticks"] == 200 and rrc["failed_ticks"] == 0 and rrc["tick"]["count"] == 200
    assert rrc["tensor_allocations_per_tick"] >= 1         # the runtime's outputs (docs/cpp.md, Limits)


@pytest.mark.slow
@needs_cpp
@needs_refine
def test_ik_tracking_loop_runs(cpp_build, refine_package, tmp_path):
    """The example's 1 kHz IK tracking loop runs for 0.2 s on recorded targets; no timing is asserted."""
    position, q0 = _inputs("refine", 50)
    np.concatenate([q0[0].numpy(), position.numpy().reshape(-1)]).tofile(tmp_path / "targets.bin")
    ik = json.loads(run_cpp(cpp_build / "dacr_rt", "ik", "--refine", refine_package / "refine.aoti.pt2",
                         "--targets", tmp_path / "targets.bin", "--seconds", 0.2, "--cpu", 0).stdout)
    assert ik["ticks"] == 200 and ik["failed_ticks"] == 0 and np.isfinite(ik["pos_err_max_m"])
