"""Export of inference modules: exported == Lightning, exported Jacobian == autograd, metadata checks refuse
tampered or mismatched files, NaN inputs are refused, broken checkpoints are refused naming the file (the folding
itself: tests/test_inference.py).

AOTInductor packages take about a minute each to build, so the fast tests export torch.export programs only
(``--no-aoti``); two slow tests check AOTI packages: an autotuned fk package, and the jacobian package without
autotuning that the C++ tests share (conftest's jacobian_aoti_package). DACR_TEST_AOTI=0 skips both
(benchmarks/latency.py builds and verifies all of them).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from conftest import ROOT, TYPE1, autograd_jacobians, first_pass_export, max_diff, names, roundoff_tol, truncated

from dacr_learn import export as dexport
from dacr_learn.cli import export as export_cli
from dacr_learn.data import generate
from dacr_learn.datamodule import KinematicsDataModule
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec
from dacr_learn.runs import load_checkpoint_model
from dacr_learn.training import FKModule, IKModule

pytestmark = pytest.mark.usefixtures("one_thread")

# Float32 outputs of one network through other kernels (eager vs torch.export / AOTInductor, GEMV vs
# GEMM, another CPU): rounding differences only. 64 float32 ulps at the O(1) scale of poses and joint
# values ≈ 7.6e-6 (3e-7 measured here), below the export's own VERIFY_TOLERANCE of 1e-5.
F32_TOL = roundoff_tol(torch.float32, 1.0)




def _train_checkpoint(module: pl.LightningModule, path: Path) -> Path:
    dm = KinematicsDataModule(robot=str(TYPE1), n_train=2000, n_val=200, n_test=200, batch_size=256)
    trainer = pl.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", devices=1)
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(path)
    return path


def _train(d: Path) -> dict:
    torch.manual_seed(0)
    _train_checkpoint(FKModule(robot=str(TYPE1), width=16, depth=2), d / "fk.ckpt")
    _train_checkpoint(IKModule(robot=str(TYPE1), width=16, depth=2), d / "ik.ckpt")
    return {}


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    """fk.ckpt and ik.ckpt (type 1, 2×16, one epoch; conftest.first_pass_export: under make test the second pass
    runs the first pass's models, which its exports were made from)."""
    d = first_pass_export("export_checkpoints", _train, tmp_path_factory)[0]
    return {"fk": d / "fk.ckpt", "ik": d / "ik.ckpt"}


@pytest.fixture(scope="module")
def exports(ckpts, tmp_path_factory) -> dict[str, Path]:
    def make(d: Path) -> dict:
        for task in ("fk", "ik"):       # through the CLI: python -m dacr_learn.export --ckpt … --out … --no-aoti
            export_cli.main(["--ckpt", str(ckpts[task]), "--out", str(d / task), "--no-aoti"])
        return {}

    d = first_pass_export("export_fk_ik", make, tmp_path_factory)[0]
    return {"fk": d / "fk", "ik": d / "ik"}


@pytest.fixture(scope="module")
def samples() -> dict[str, torch.Tensor]:
    return generate(RobotSpec.from_yaml(TYPE1), 64, seed=3)


# ------------------------------------------------------------------------------------------
# Exported modules == the Lightning model
# ------------------------------------------------------------------------------------------


def test_exported_fk_and_jacobian_equal_lightning(ckpts, exports, samples):
    lit = FKModule.load_from_checkpoint(ckpts["fk"], map_location="cpu").eval()
    fk, jac = dexport.load(exports["fk"] / "fk.pt2"), dexport.load(exports["fk"], "jacobian")
    q = samples["q"]
    with torch.no_grad():
        ref = lit(q)
    assert max_diff(fk(q), ref) <= F32_TOL
    pose, jac_f, jac_q = jac(q)
    assert max_diff(pose, ref) <= F32_TOL
    assert jac_f.shape == (64, 6, 3) and jac_q.shape == (64, 6, 4)
    assert fk.kind == "export" and fk.metadata["robot"]["name"] == "type1"


def test_exported_ik_equals_lightning_and_satisfies_constraint(ckpts, exports, samples):
    lit = IKModule.load_from_checkpoint(ckpts["ik"], map_location="cpu").eval()
    ik = dexport.load(exports["ik"], "ik")
    with torch.no_grad():
        ref = lit(samples["pose"])
    q = ik(samples["pose"])
    assert max_diff(q, ref) <= F32_TOL
    spec = RobotSpec.from_yaml(TYPE1)
    q64 = q.double()
    residual = (q64 - ClarkeDecoder(spec).double()(ClarkeEncoder(spec).double()(q64))).abs().max().item()
    assert residual <= 1e-6                                  # the IK target: joints on the constraint to 1 µm


def test_loaded_module_handles_batch_dims_and_dtype(exports, samples):
    fk = dexport.load(exports["fk"], "fk")
    q = samples["q"][:6]
    batched = fk(q)
    assert fk(q[0]).shape == (4, 4) and max_diff(fk(q[0]), batched[0]) <= F32_TOL # GEMV vs GEMM rounding
    assert fk(q.reshape(2, 3, 4)).shape == (2, 3, 4, 4)
    assert max_diff(fk(q.reshape(2, 3, 4)).reshape(6, 4, 4), batched) <= F32_TOL
    out64 = fk(q.double())
    assert out64.dtype == torch.float64 and max_diff(out64, batched) <= F32_TOL


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("DACR_TEST_AOTI") == "0",
                    reason="DACR_TEST_AOTI=0 skips the ~1 min AOTInductor build")
def test_aoti_package_equals_lightning(ckpts, samples, tmp_path):
    """The fk's package, autotuned (the package without autotuning: the next test's jacobian)."""
    meta = dexport.export_checkpoint(ckpts["fk"], tmp_path, aoti=("fk",), autotune=True)
    fk = dexport.load(tmp_path, "fk")
    lit = FKModule.load_from_checkpoint(ckpts["fk"], map_location="cpu").eval()
    with torch.no_grad():
        assert fk.kind == "aoti" and max_diff(fk(samples["q"]), lit(samples["q"])) <= F32_TOL
    assert meta["max_abs_deviation"]["fk.aoti.pt2"] <= F32_TOL and meta["aoti_autotune"] is True


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("DACR_TEST_AOTI") == "0",
                    reason="DACR_TEST_AOTI=0 skips the ~1 min AOTInductor build")
def test_aoti_jacobian_package_equals_lightning(jacobian_aoti_package):
    """The jacobian's package without autotuning (conftest's, shared with the C++ tests): its pose is the Lightning
    model's, its Jacobians are jacrev's of the float64 model."""
    meta = dexport.read_metadata(jacobian_aoti_package)
    assert meta["max_abs_deviation"]["jacobian.aoti.pt2"] <= F32_TOL and meta["aoti_autotune"] is False
    jac = dexport.load(jacobian_aoti_package, "jacobian")
    lit = FKModule.load_from_checkpoint(jacobian_aoti_package.parent / "fk.ckpt", map_location="cpu").eval()
    q = generate(lit.spec, 64, seed=3)["q"]
    with torch.no_grad():
        pose, jac_f, jac_q = jac(q)
        assert jac.kind == "aoti" and max_diff(pose, lit(q)) <= F32_TOL
    model = lit.model.double()
    for i in range(4):
        ref_f, ref_q = autograd_jacobians(model, lit.spec, q[i].double())
        assert max_diff(jac_q[i], ref_q) <= 1e-4 * ref_q.abs().max().item()
        assert max_diff(jac_f[i], ref_f) <= 1e-4 * ref_f.abs().max().item()


def test_autotune_needs_the_aoti_packages(ckpts, exports, tmp_path, capsys):
    assert dexport.read_metadata(exports["fk"])["aoti_autotune"] is False      # the default
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--ckpt", str(ckpts["fk"]), "--out", str(tmp_path / "x"), "--no-aoti", "--autotune"])
    assert exit_info.value.code == 2 and "--autotune tunes the AOTInductor packages" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# Exported float32 Jacobian == autograd of the FK
# ------------------------------------------------------------------------------------------


def test_exported_float32_jacobian_matches_jacrev(ckpts, exports, samples):
    lit = FKModule.load_from_checkpoint(ckpts["fk"], map_location="cpu").eval()
    model, spec = lit.model.double(), lit.spec
    _, jac_f, jac_q = dexport.load(exports["fk"], "jacobian")(samples["q"][:4])
    for i in range(4):
        ref_f, ref_q = autograd_jacobians(model, spec, samples["q"][i].double())
        assert max_diff(jac_q[i], ref_q) <= 1e-4 * ref_q.abs().max().item()
        assert max_diff(jac_f[i], ref_f) <= 1e-4 * ref_f.abs().max().item()


# ------------------------------------------------------------------------------------------
# Metadata: mismatched or tampered files are refused
# ------------------------------------------------------------------------------------------


@pytest.fixture()
def fk_copy(exports, tmp_path) -> Path:
    return Path(shutil.copytree(exports["fk"], tmp_path / "fk"))


def test_metadata_records_spec_units_and_checkpoint(ckpts, exports):
    meta = dexport.read_metadata(exports["fk"])
    assert meta["robot"] == RobotSpec.from_yaml(TYPE1).to_dict() and meta["features"] == "clarke"
    assert meta["source_checkpoint"]["sha256"] == dexport.file_sha256(ckpts["fk"])
    assert meta["units"]["joint_lengths"] == "m" and meta["dtype"] == "float32"
    assert all(v <= F32_TOL for v in meta["max_abs_deviation"].values())


def test_tampered_module_file_is_refused(fk_copy):
    with open(fk_copy / "fk.pt2", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ValueError, match="checksum mismatch"):
        dexport.load(fk_copy / "fk.pt2")


def test_file_from_another_export_is_refused(fk_copy, exports):
    shutil.copy(exports["ik"] / "ik.pt2", fk_copy / "fk.pt2")
    with pytest.raises(ValueError, match="checksum mismatch"):
        dexport.load(fk_copy, "fk")
    shutil.copy(exports["ik"] / "ik.pt2", fk_copy / "ik.pt2")
    with pytest.raises(ValueError, match="not a file of this export"):
        dexport.load(fk_copy / "ik.pt2")


def test_tampered_metadata_is_refused(fk_copy):
    meta = json.loads((fk_copy / dexport.METADATA_FILE).read_text())
    meta["robot"]["segments"][0]["radius"] = 0.009
    (fk_copy / dexport.METADATA_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="metadata was modified"):
        dexport.load(fk_copy, "fk")
    (fk_copy / dexport.METADATA_FILE).unlink()
    with pytest.raises(FileNotFoundError, match="no export metadata"):
        dexport.load(fk_copy / "fk.pt2")


def test_expectations_are_checked(exports, ckpts):
    assert dexport.load(exports["fk"], "fk", robot=TYPE1, features="clarke", checkpoint=ckpts["fk"]) is not None
    with pytest.raises(ValueError, match="robot spec mismatch"):
        dexport.load(exports["fk"], "fk", robot=ROOT / "configs" / "robots" / "type3.yaml")
    with pytest.raises(ValueError, match="feature mode mismatch"):
        dexport.load(exports["fk"], "fk", features="raw")
    with pytest.raises(ValueError, match="different checkpoint"):
        dexport.load(exports["fk"], "fk", checkpoint=ckpts["ik"])
    with pytest.raises(ValueError, match="expected one of"):
        dexport.load(exports["fk"], "ik")


# ------------------------------------------------------------------------------------------
# Invalid inputs give clear errors, never NaN outputs
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("task,name,key", [("fk", "fk", "q"), ("fk", "jacobian", "q"), ("ik", "ik", "pose")])
def test_nan_and_invalid_inputs_are_refused(exports, samples, task, name, key):
    module = dexport.load(exports[task], name)
    x = samples[key][:4].clone()
    for bad in (float("nan"), float("inf")):
        x.view(-1)[1] = bad
        with pytest.raises(ValueError, match="expected finite values"):
            module(x)
    with pytest.raises(ValueError, match="expected .* of shape"):
        module(samples[key][:4, ..., :2])
    with pytest.raises(ValueError, match="floating-point"):
        module(samples[key][:4].long())


def test_autotuned_export_does_not_print_inductors_timing_tables():
    """python -m dacr_learn.export --autotune printed "AUTOTUNE addmm(…)" tables and "Autotune Choices Stats"
    JSON for every tuned product (Inductor writes them to stderr); the export's Inductor options turn both off."""
    import torch._inductor.config as inductor_config

    from dacr_learn.export import AUTOTUNE_CONFIGS

    assert AUTOTUNE_CONFIGS["autotune_num_choices_displayed"] == 0
    assert AUTOTUNE_CONFIGS["max_autotune_report_choices_stats"] is False
    assert all(hasattr(inductor_config, key) for key in AUTOTUNE_CONFIGS)     # names of this torch's options


# --------------------------------------------------------------------------------------------------
# Checkpoints given to export: a broken file gives a ValueError naming it
# --------------------------------------------------------------------------------------------------


def _checkpoint(**changes) -> dict:
    """A minimal Lightning checkpoint of an untrained FKModule (no Trainer needed)."""
    module = FKModule(robot=str(TYPE1), width=8, depth=1)
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "pytorch-lightning_version": "2.6.0"}
    for key, value in changes.items():
        if value is None:
            ckpt.pop(key)
        else:
            ckpt[key] = value
    return ckpt


def test_well_formed_checkpoint_loads(tmp_path):
    """Positive control for the refusals below: the same construction, unchanged, loads."""
    torch.save(_checkpoint(), tmp_path / "ok.ckpt")
    task, model = load_checkpoint_model(tmp_path / "ok.ckpt")
    assert task == "fk" and model.net[0].out_features == 8


def test_checkpoint_that_is_not_a_torch_file(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint at all\n" * 10)
    with pytest.raises(ValueError, match=names(garbage, "expected an FKModule/IKModule/SamplerModule checkpoint",
                                               "found a file of 240 bytes", "not a complete torch.save")):
        load_checkpoint_model(garbage)
    for keep in (0, 1, 100, -10):
        torch.save(_checkpoint(), tmp_path / "cut.ckpt")
        cut = truncated(tmp_path / "cut.ckpt", keep)
        with pytest.raises(ValueError, match=names(cut, "not a complete torch.save archive")) as err:
            load_checkpoint_model(cut)
        assert err.value.__cause__ is not None
    with pytest.raises(FileNotFoundError, match=names(tmp_path / "missing.ckpt", "no such file")):
        load_checkpoint_model(tmp_path / "missing.ckpt")


def test_export_cli_prints_the_error_not_a_traceback(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match=names(garbage, "not a complete torch.save")):
        export_cli.main(["--ckpt", str(garbage), "--out", str(tmp_path / "out")])
    run = subprocess.run([sys.executable, "-m", "dacr_learn.export", "--ckpt", str(garbage), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.returncode != 0 and "Traceback" not in run.stderr, run.stderr
    assert str(garbage) in run.stderr and "not a complete torch.save archive" in run.stderr, run.stderr
    assert "RuntimeWarning" not in run.stderr, run.stderr     # runpy: the package must not import its own CLI module


NOT_OURS = {   # case: (content of the torch file, parts of the message)
    "tensor": (lambda: torch.zeros(3), ("found a torch file holding a Tensor",)),
    "plain dict": (lambda: {"weights": torch.zeros(3)}, ("found a dict without", "state_dict", "hyper_parameters")),
    "no hyper-parameters": (lambda: _checkpoint(hyper_parameters=None), ("found a dict without", "hyper_parameters")),
    "no robot": (lambda: _checkpoint(hyper_parameters={"features": "clarke"}), ("without a robot spec",)),
    "bad robot": (lambda: _checkpoint(hyper_parameters={"robot": {"segments": []}}),
                  ("hyper_parameters.robot", "segments: got []", "expected a non-empty list")),
    "other weights": (lambda: _checkpoint(state_dict={"layer.weight": torch.zeros(2)}),
                      ("without model.front.norm / model.in_norm", "layer.weight")),
    "weights of another width": (
        lambda: _checkpoint(state_dict=FKModule(robot=str(TYPE1), width=16, depth=1).state_dict()),
        ("FKModule cannot load", "size mismatch")),
}


@pytest.mark.parametrize("case", NOT_OURS)
def test_torch_file_that_is_not_our_checkpoint(tmp_path, case):
    content, parts = NOT_OURS[case]
    path = tmp_path / "other.ckpt"
    torch.save(content(), path)
    with pytest.raises(ValueError, match=names(path, *parts)):
        load_checkpoint_model(path)


def test_export_metadata_that_is_not_json(tmp_path):
    meta = tmp_path / dexport.METADATA_FILE
    for text, found in (("{oops", "found invalid JSON"), ("[1, 2]", "found a JSON list")):
        meta.write_text(text)
        with pytest.raises(ValueError, match=names(meta, "expected the metadata.json of an export", found)):
            dexport.read_metadata(tmp_path)


def test_inlined_products_leave_no_matrix_product_and_equal_the_program():
    """inline_products (the option of packages of small products): no mm/bmm/addmm/matmul op left, same outputs
    (float64, to roundoff) on another batch size than the example's (the batch dim stays dynamic)."""
    from dacr_learn.deploy.export import export_program, inline_products

    class Products(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.linear = torch.nn.Linear(5, 4).double()

        def forward(self, x, y):
            return self.linear(x) @ y, torch.bmm(x.unsqueeze(1), x.unsqueeze(-1)).squeeze()

    g = torch.Generator().manual_seed(0)
    x, y = (torch.randn(3, 5, generator=g, dtype=torch.float64), torch.randn(3, 4, 4, generator=g,
                                                                             dtype=torch.float64))
    program = export_program(Products(), (x, y))
    inlined = inline_products(program)
    ops = {str(n.target) for n in inlined.graph.nodes if n.op == "call_function"}
    assert not any(name in op for op in ops for name in ("mm.", "bmm.", "addmm.", "matmul."))
    x, y = x.repeat(3, 1), y.repeat(3, 1, 1)
    for want, got in zip(program.module()(x, y), inlined.module()(x, y), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)


def test_programs_are_exported_for_contiguous_inputs():
    """A package assumes its example's strides and its callers (C++, the package's runner) pass contiguous tensors:
    an example that is a strided view (the batched kinematics' tips are batch-last views) is exported as contiguous,
    so the position-only IK refinement's package computes what the eager module does (it read its target with the
    view's strides before: deviations of 0.05–0.3, garbage at other batch sizes)."""
    from dacr_learn.deploy.export import export_program

    class Shift(torch.nn.Module):
        def forward(self, target, q):
            return q[:, :3] + target

    target = torch.randn(3, 4, dtype=torch.float64).t()[:, :3]                     # (4, 3) view, strides (1, 4)
    assert not target.is_contiguous()
    program = export_program(Shift(), (target, torch.randn(4, 5, dtype=torch.float64)))
    inputs = [n.meta["val"] for n in program.graph.nodes if n.op == "placeholder"]
    assert len(inputs) == 2 and all(t.is_contiguous() for t in inputs)
    assert torch.equal(program.module()(target, torch.zeros(4, 5, dtype=torch.float64)), target)
