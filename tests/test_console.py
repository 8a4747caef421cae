"""dacr_learn.console: the third-party warning filters (each hides its one real warning, nothing else),
first_user_error through jsonargparse's wrapping, run_cli's one-line errors, and the CLIs run as a
user runs them: a typo in a robot YAML or a missing path is the first line they see, ``error: …``."""
from __future__ import annotations

import copy
import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from conftest import ROOT
from hardware_testkit import V4_CALIBRATED

from dacr_learn import console

TYPO = 'segments:\n  - {type: "0", lenght: 0.1, radius: 0.008, joints: 4}\n'
LEAFSPEC = ("`isinstance(treespec, LeafSpec)` is deprecated, use `isinstance(treespec, TreeSpec) and "
            "treespec.is_leaf()` instead.")


@pytest.fixture
def typo_robot(tmp_path) -> Path:
    path = tmp_path / "robot.yaml"
    path.write_text(TYPO)
    return path


def shown(trigger, quiet: bool) -> list[str]:
    """The warnings ``trigger()`` shows under Python's default filters, with or without the console's."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.resetwarnings()
        if quiet:
            console.quiet_third_party_warnings()
        warnings.filterwarnings("always", append=True)       # after ours: what passes them is recorded
        trigger()
    return [f"{w.category.__name__}: {w.message}" for w in caught]


# ---- warning filters: each real warning hidden, unrelated ones not ----------------------------------


def _lightning_pytree():
    from lightning.pytorch.utilities._pytree import _tree_flatten

    _tree_flatten(1.0)                 # builds a LeafSpec, as Lightning does for every batch


def _fx_graph_copy():
    import torch.utils._pytree as pytree

    copy.deepcopy(pytree.tree_flatten(1.0)[1])  # a LeafSpec re-created through copyreg, as AOTInductor does


@pytest.mark.parametrize("trigger", [_lightning_pytree, _fx_graph_copy])
def test_leafspec_deprecation_is_hidden(trigger):
    assert shown(trigger, quiet=False) == [f"FutureWarning: {LEAFSPEC}"]      # the real warning, raised
    assert shown(trigger, quiet=True) == []


def _typed_storage_message() -> str:
    """torch's own text of the TypedStorage deprecation (tensor.storage())."""
    import torch

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.zeros(1).storage()
    return next(str(w.message) for w in caught if w.category is UserWarning)


def test_typed_storage_deprecation_of_inductor_autotuning_is_hidden():
    """Raised in torch/_inductor/select_algorithm.py while --autotune times kernels (too slow to run here):
    the real message, issued from that module."""
    message = _typed_storage_message()

    def emit():
        warnings.warn_explicit(message, UserWarning, "select_algorithm.py", 4799,
                               module="torch._inductor.select_algorithm")
    assert shown(emit, quiet=False) == [f"UserWarning: {message}"]
    assert shown(emit, quiet=True) == []


@pytest.mark.parametrize(("module", "message", "category"), [
    ("copyreg", LEAFSPEC, FutureWarning), ("lightning.pytorch.utilities._pytree", LEAFSPEC, FutureWarning),
    ("torch._inductor.select_algorithm", "TypedStorage is deprecated.", UserWarning)])
def test_warning_filters_hide_nothing_else(module, message, category):
    other = DeprecationWarning if category is not DeprecationWarning else UserWarning

    def emit():
        warnings.warn_explicit(message, category, "ours.py", 1, module="dacr_learn.something")   # other module
        warnings.warn_explicit(message, other, f"{module}.py", 2, module=module)                 # other category
        warnings.warn_explicit("another message", category, f"{module}.py", 3, module=module)    # other message
        warnings.warn_explicit(message, category, "x.py", 4, module=module + "_extra")         # longer name
    assert len(shown(emit, quiet=True)) == 4
    assert shown(lambda: warnings.warn_explicit(message, category, "m.py", 5, module=module), quiet=True) == []


@pytest.fixture
def lightning_records():
    """INFO records that reach the handlers of Lightning's rank-zero logger; the advert filter removed after."""
    import lightning.pytorch  # noqa: F401  (points the rank_zero logger at lightning.pytorch)

    records: list[str] = []
    handler = logging.Handler(logging.DEBUG)
    handler.emit = lambda record: records.append(record.getMessage())
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    logger.removeFilter(console._DROP_ADVERTS)           # installed by an earlier test of this process
    level = logger.level
    logger.setLevel(logging.INFO)     # an earlier test may have raised lightning.pytorch's level (ablation runner)
    logger.addHandler(handler)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.removeFilter(console._DROP_ADVERTS)
        logger.setLevel(level)


def _trainer():
    import lightning.pytorch as pl

    pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)


LITMODELS_TIP = ("💡 Tip: For seamless cloud uploads and versioning, try installing "
                 "[litmodels](https://pypi.org/project/litmodels/) to enable LitModelCheckpoint, which syncs "
                 "automatically with the Lightning model registry.")


def test_lightning_adverts_are_dropped_and_its_other_lines_kept(lightning_records):
    from lightning.pytorch.utilities.rank_zero import rank_zero_info

    _trainer()                                            # the real litlogger advert
    rank_zero_info(LITMODELS_TIP)                         # callback_connector's text, on the same logger
    assert sum(r.startswith("💡 Tip: For seamless") for r in lightning_records) == 2, lightning_records
    lightning_records.clear()
    console.quiet_third_party_warnings()
    _trainer()
    rank_zero_info(LITMODELS_TIP)
    rank_zero_info("💡 Tip: something a user can use")   # not one of the two known adverts
    assert not any("For seamless" in r for r in lightning_records), lightning_records
    assert "💡 Tip: something a user can use" in lightning_records
    assert any(r.startswith("GPU available") for r in lightning_records), lightning_records


# ---- first_user_error -------------------------------------------------------------------------------


def _raised(fn) -> BaseException:
    try:
        fn()
    except BaseException as err:
        return err
    raise AssertionError("nothing raised")


def test_first_user_error_behind_jsonargparse_union(typo_robot):
    """LightningCLI's model (subclass mode: Optional[KinematicsModule]) whose __init__ raises our ValueError:
    jsonargparse raises its own ValueError from ours, and ours is the one that names the file."""
    from jsonargparse import ArgumentParser

    from dacr_learn.training import KinematicsModule

    for hint in (KinematicsModule | None, int | KinematicsModule):   # ours: the __cause__ / the 2nd member's error
        parser = ArgumentParser(exit_on_error=False)
        parser.add_argument("--model", type=hint)
        cfg = parser.parse_args(["--model", "dacr_learn.training.FKModule", "--model.robot", str(typo_robot)])
        err = _raised(lambda: parser.instantiate(cfg))  # noqa: B023
        assert type(err) is ValueError and str(err).startswith("Does not validate against any of the Union")
        found = console.first_user_error(err)
        assert str(found).startswith(f"{typo_robot}: segments[0]: got ['lenght']"), found


def test_first_user_error_behind_argument_errors(typo_robot):
    """A parse-time type conversion that raised ours arrives as argparse.ArgumentError wrappers."""
    import argparse

    from jsonargparse import ArgumentParser

    from dacr_learn.robot import RobotSpec

    parser = ArgumentParser(exit_on_error=False)
    parser.add_argument("--robot", type=RobotSpec.from_yaml)
    err = _raised(lambda: parser.parse_args(["--robot", str(typo_robot)]))
    assert isinstance(err, argparse.ArgumentError)
    assert str(console.first_user_error(err)).startswith(f"{typo_robot}: segments[0]")


# Lightning 2.6's cli.py calls jsonargparse APIs deprecated in 4.49 (hidden outside pytest: DeprecationWarning)
@pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli")
def test_first_user_error_through_lightning_cli(typo_robot, monkeypatch):
    """train.py's path: LightningCLI instantiating a model whose robot YAML has a typo."""
    from lightning.pytorch.cli import LightningCLI

    from dacr_learn.datamodule import KinematicsDataModule
    from dacr_learn.training import KinematicsModule

    monkeypatch.setattr(sys, "argv", ["train.py"])
    err = _raised(lambda: LightningCLI(
        KinematicsModule, KinematicsDataModule, subclass_mode_model=True, run=False, save_config_callback=None,
        seed_everything_default=False,
        args=["--model", "dacr_learn.training.FKModule", "--model.robot", str(typo_robot),
              "--data.robot", str(typo_robot), "--trainer.logger", "false"]))
    assert str(console.first_user_error(err)).startswith(f"{typo_robot}: segments[0]: got ['lenght']")


def test_first_user_error_plain_chains():
    def wrapped():
        try:
            raise KeyError("x")
        except KeyError as err:
            raise ValueError("robot.yaml: bad") from err

    assert str(console.first_user_error(_raised(wrapped))) == "robot.yaml: bad"
    assert console.first_user_error(RuntimeError("a bug")) is None

    def bug_hiding_nothing():
        try:
            raise ValueError("inner")
        except ValueError:
            raise RuntimeError("bug") from None          # suppressed: not a user error

    assert console.first_user_error(_raised(bug_hiding_nothing)) is None
    missing = FileNotFoundError("data/x.csv: no such file")
    assert console.first_user_error(missing) is missing


# ---- run_cli ----------------------------------------------------------------------------------------


def _fail(exc: BaseException):
    def main(argv):
        print("partial output")
        raise exc
    return main


def test_run_cli_prints_one_line_for_a_user_error(capsys, monkeypatch):
    monkeypatch.delenv(console.DEBUG_ENV, raising=False)
    assert console.run_cli(_fail(ValueError("robot.yaml: segments[0].length: got 'x', expected a number")), []) == 2
    out, err = capsys.readouterr()
    assert out == "partial output\n"
    assert err == "error: robot.yaml: segments[0].length: got 'x', expected a number\n"
    assert console.run_cli(_fail(FileNotFoundError("data/train.csv: no such file")), []) == 2
    assert capsys.readouterr().err == "error: data/train.csv: no such file\n"


def test_run_cli_debug_shows_the_traceback(capsys, monkeypatch):
    monkeypatch.setenv(console.DEBUG_ENV, "1")
    assert console.run_cli(_fail(ValueError("robot.yaml: bad")), []) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1] == "error: robot.yaml: bad"


def test_run_cli_interrupt_and_bugs(capsys):
    assert console.run_cli(_fail(KeyboardInterrupt()), []) == 130
    assert [line for line in capsys.readouterr().err.splitlines() if line] == ["interrupted (Ctrl-C)"]
    with pytest.raises(RuntimeError, match="a bug"):
        console.run_cli(_fail(RuntimeError("a bug")), [])
    assert console.run_cli(lambda argv: {"result": 1}, []) == 0


# ---- the CLIs, as a user runs them -------------------------------------------------------------------


def _cli_cases(tmp: Path, typo: Path) -> dict[str, tuple[list[str], str]]:
    """case: (command after the interpreter, what the first line must name)."""
    ablation = tmp / "ablation.yaml"
    ablation.write_text((ROOT / "configs" / "ablation" / "default.yaml").read_text()
                        .replace("configs/robots/type0_n4.yaml", str(typo)))
    return {
        "export, missing checkpoint": (["-m", "dacr_learn.export", "--ckpt", str(tmp / "none.ckpt"),
                                        "--out", str(tmp / "out")], str(tmp / "none.ckpt")),
        "hardware, typo in the robot": (["-m", "dacr_learn.hardware", "--data", str(ROOT / "data" / "ftdcr_v4"),
                                         "--robot", str(typo), "--out", str(tmp / "run")], f"{typo}: segments[0]"),
        "hardware, missing data": (["-m", "dacr_learn.hardware", "--data", str(tmp / "nodata"), "--robot",
                                    str(V4_CALIBRATED), "--out", str(tmp / "run")], str(tmp / "nodata" / "train.csv")),
        "ablation, typo in a robot": (["-m", "dacr_learn.ablation", "--config", str(ablation), "--quick",
                                       "--out", str(tmp / "abl")], f"{typo}: segments[0]"),
        "control example, missing export": ([str(ROOT / "examples" / "control_hardware_model.py"), "--export",
                                             str(tmp / "noexport"), "--out", str(tmp / "ctl")], str(tmp / "noexport")),
    }


@pytest.mark.slow            # one CLI subprocess per case: behaviour, not float order
@pytest.mark.parametrize("case", ["export, missing checkpoint", "hardware, typo in the robot",
                                  "hardware, missing data", "ablation, typo in a robot",
                                  "control example, missing export"])
def test_cli_first_line_is_the_error(tmp_path, typo_robot, case):
    args, names = _cli_cases(tmp_path, typo_robot)[case]
    run = subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env={k: v for k, v in os.environ.items() if k != console.DEBUG_ENV})
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert run.returncode == 2, run.stderr
    assert lines and lines[0].startswith("error: ") and names in lines[0], lines
    assert "Traceback" not in run.stderr and len(lines) == 1, lines
