"""Runs a user can trust: train.py never destroys an earlier run, resumes keep the whole recording,
`test` writes beside the fit, a checkpoint of another model is refused, interruptions say how to resume.

Run folders and the loader (dacr_learn.runs) are tested directly; the CLI behaviour through train.main
in-process, and SIGTERM / Ctrl-C through a train.py subprocess (a callback sends the signal mid-epoch).
"""
from __future__ import annotations

import hashlib
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import ROOT, write_run_config
from rerun.chunk import RrdReader

import train
from dacr_learn import runs
from dacr_learn.training import FKModule

STEPS_PER_EPOCH = 2000 // 64 + 1          # write_run_config: 2 000 samples, batch 64


def digests(folder: Path) -> dict[str, str]:
    """sha256 of every file below ``folder`` (relative path → hex)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def recording(folder: Path) -> tuple[set[str], list[int]]:
    """(recording ids, sorted steps of every logged train-loss row) over all rerun*.rrd parts in ``folder``."""
    ids, steps = set(), []
    for part in sorted(folder.glob("rerun*.rrd")):
        ids |= {r.recording_id for r in RrdReader(part).recordings()}
        for chunk in RrdReader(part).stream():
            if chunk.entity_path == "/metrics/train/loss":
                batch = chunk.to_record_batch()
                if "step" in batch.schema.names:            # the static series style has no time column
                    steps += batch.column("step").to_pylist()
    return ids, sorted(steps)


def run_train(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])}
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *args], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)


# ---- dacr_learn.runs: folders and the loader ----------------------------------------------------------

def test_new_numbered_dir_never_reuses_a_folder(tmp_path):
    first = runs.new_numbered_dir(tmp_path / "r", "version_")
    second = runs.new_numbered_dir(tmp_path / "r", "version_")
    (tmp_path / "r" / "version_7").mkdir()
    assert [first.name, second.name] == ["version_0", "version_1"]
    assert runs.new_numbered_dir(tmp_path / "r", "version_").name == "version_8"
    assert [p.name for p in runs.versions(tmp_path / "r")] == ["version_0", "version_1", "version_7", "version_8"]


def test_run_info_is_written_once(tmp_path):
    info = runs.write_run_info(tmp_path, run_name="x")
    assert runs.read_run_info(tmp_path) == info and len(info["recording_id"]) == 36
    with pytest.raises(ValueError, match="already has a run.json"):
        runs.write_run_info(tmp_path)
    assert runs.read_run_info(tmp_path / "elsewhere") == {}


def test_find_checkpoint_resolves_run_version_and_file(tmp_path):
    for v in (0, 1, 2):
        (tmp_path / f"version_{v}" / "checkpoints").mkdir(parents=True)
    for v in (0, 1):
        (tmp_path / f"version_{v}" / "checkpoints" / "last.ckpt").write_bytes(b"x")
    newest = tmp_path / "version_1" / "checkpoints" / "last.ckpt"      # version_2 has no checkpoint yet
    assert runs.find_checkpoint(tmp_path) == newest
    assert runs.find_checkpoint(tmp_path / "version_0") == tmp_path / "version_0" / "checkpoints" / "last.ckpt"
    assert runs.find_checkpoint(newest) == newest
    with pytest.raises(FileNotFoundError, match="no checkpoints/last.ckpt"):
        runs.find_checkpoint(tmp_path / "version_2")
    with pytest.raises(FileNotFoundError, match="no such file or folder"):
        runs.find_checkpoint(tmp_path / "missing")


# ---- train.py fit / test -----------------------------------------------------------------------------

def test_second_fit_is_a_new_run_and_leaves_the_first_byte_identical(tmp_path):
    config = str(write_run_config(tmp_path, epochs=2))
    train.main(["fit", "--config", config])
    first = tmp_path / "runs" / "smoke" / "version_0"
    before = digests(first)
    second_cli = train.main(["fit", "--config", config])
    second = tmp_path / "runs" / "smoke" / "version_1"
    assert digests(first) == before                           # nothing of the first run changed
    assert second_cli.trainer.global_step == 2 * STEPS_PER_EPOCH   # trained from scratch, not resumed
    for run in (first, second):
        assert {"run.json", "config.yaml", "metrics.json", "rerun.rrd", "checkpoints/last.ckpt"} <= set(digests(run))
        ids, steps = recording(run)
        assert len(ids) == 1 and steps[0] <= 5 and steps[-1] >= 2 * STEPS_PER_EPOCH - 5   # whole curve
    assert recording(first)[0] != recording(second)[0]         # two recordings, not one


def test_a_resume_that_fails_before_its_first_step_keeps_the_runs_checkpoint(tmp_path, monkeypatch):
    """An error in set-up (before the checkpoint is restored) used to save the untrained model over the run's
    last.ckpt; now nothing is saved before the first step, and a fresh run that fails there leaves none."""
    config = str(write_run_config(tmp_path, epochs=1))
    train.main(["fit", "--config", config])
    last = tmp_path / "runs" / "smoke" / "version_0" / "checkpoints" / "last.ckpt"
    before = hashlib.sha256(last.read_bytes()).hexdigest()

    def failing_setup(self, stage):
        raise ValueError("model.lr: a set-up error for this test")

    monkeypatch.setattr(FKModule, "setup", failing_setup)
    assert train.run_command_line(["fit", "--config", config, "--ckpt_path", "last"]) == 2
    assert hashlib.sha256(last.read_bytes()).hexdigest() == before
    assert train.run_command_line(["fit", "--config", config]) == 2          # a fresh run: version_1
    assert not (tmp_path / "runs" / "smoke" / "version_1" / "checkpoints" / "last.ckpt").exists()


def test_another_robot_under_the_same_run_name_does_not_touch_the_first(tmp_path):
    train.main(["fit", "--config", str(write_run_config(tmp_path, epochs=1))])
    first = tmp_path / "runs" / "smoke" / "version_0"
    before = digests(first)
    other = write_run_config(tmp_path, epochs=1, robot="configs/robots/tdcr_3seg_coupled.yaml")
    cli = train.main(["fit", "--config", str(other)])
    assert digests(first) == before
    assert cli.model.spec.num_joints == 12
    assert torch.load(tmp_path / "runs/smoke/version_1/checkpoints/last.ckpt", weights_only=True)["global_step"] > 0


def test_checkpoint_of_another_model_is_refused_naming_both(tmp_path):
    config = write_run_config(tmp_path, epochs=1)
    train.main(["fit", "--config", str(config)])
    first = tmp_path / "runs" / "smoke" / "version_0"
    before = digests(first)
    other = write_run_config(tmp_path, epochs=1, robot="configs/robots/tdcr_3seg_coupled.yaml")
    for sub in ("fit", "test"):
        with pytest.raises(ValueError) as err:
            train.main([sub, "--config", str(other), "--ckpt_path", "last"])
        message = str(err.value)
        assert "\n" not in message
        assert "holds an FKModule for robot 'type1' (1 segment, 4 joints)" in message
        assert "the config asks for an FKModule for robot 'tdcr-3seg' (3 segments, 12 joints)" in message
    with pytest.raises(ValueError, match="width 32.*width 64"):
        train.main(["fit", "--config", str(config), "--model.init_args.width", "64", "--ckpt_path", "last"])
    assert digests(first) == before
    assert runs.versions(tmp_path / "runs" / "smoke") == [first]      # no folder was made for the refusals


def test_test_writes_its_own_folder_and_keeps_the_fit_files(tmp_path):
    config = str(write_run_config(tmp_path, epochs=1))
    train.main(["fit", "--config", config])
    run = tmp_path / "runs" / "smoke" / "version_0"
    before = digests(run)
    for k in (0, 1):
        train.main(["test", "--config", config, "--ckpt_path", "last"])
        out = run / f"test_{k}"
        summary = json.loads((out / "metrics.json").read_text())
        assert summary["checkpoint"] == str(run / "checkpoints" / "last.ckpt")
        assert summary["pos_err_mean_mm"] == pytest.approx(json.loads((run / "metrics.json").read_text())
                                                           ["pos_err_mean_mm"], rel=1e-5)
        assert (out / "rerun.rrd").stat().st_size > 0
    assert {k: v for k, v in digests(run).items() if not k.startswith("test_")} == before


def test_resuming_with_another_schedule_is_refused_naming_both(tmp_path):
    config = str(write_run_config(tmp_path, epochs=1))
    train.main(["fit", "--config", config])
    for args, what in ((["--trainer.max_epochs", "3"], "trainer.max_epochs 1; the config asks for 3"),
                       (["--data.n_train", "4000"], "data.n_train 2000; the config asks for 4000")):
        with pytest.raises(ValueError, match=what):
            train.main(["fit", "--config", config, *args, "--ckpt_path", "last"])


def test_test_needs_a_checkpoint(tmp_path):
    config = str(write_run_config(tmp_path, epochs=1))
    with pytest.raises(ValueError, match="needs --ckpt_path"):
        train.main(["test", "--config", config])
    with pytest.raises(ValueError, match="--ckpt_path last: .*no such file or folder"):
        train.main(["test", "--config", config, "--ckpt_path", "last"])
    assert not (tmp_path / "runs").exists()


def test_load_model_from_a_run_folder_predicts_like_the_trained_module(tmp_path):
    cli = train.main(["fit", "--config", str(write_run_config(tmp_path, epochs=1))])
    model = runs.load_model(tmp_path / "runs" / "smoke")
    q = cli.datamodule.splits["test"]["q"][:16]
    cli.model.eval()
    with torch.no_grad():
        expected = cli.model(q)
        pose = model(q)
    assert model.task == "fk" and model.spec == cli.model.spec and not model.training
    assert pose.shape == (16, 4, 4)
    torch.testing.assert_close(pose, expected)
    assert isinstance(FKModule.load_from_checkpoint(runs.find_checkpoint(tmp_path / "runs/smoke")), FKModule)
    # a newcomer's inputs: the float64 joints ResolvedRateController.step returns are cast (not a dtype error),
    with torch.no_grad():
        pose64 = model(q.double())
    assert pose64.dtype == torch.float32 and torch.equal(pose64, pose)
    # joint lengths in millimetres are refused instead of giving a tip metres away
    with pytest.raises(ValueError, match=r"joint vector: expected joint lengths in metres.*millimetres"):
        model(1e3 * q)
    with torch.no_grad():                                       # at the robot's limits: still accepted
        model(q * 1.5)


# ---- interruptions (subprocess: real signals) ---------------------------------------------------------

def _resume_command(stderr: str) -> list[str]:
    lines = stderr.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("Resume this run with:"))
    words = shlex.split(lines[at + 1])
    assert Path(words[1]).name == "train.py"
    return words[2:]


# The stops of the interrupted run: SIGTERM (a scheduler) in the middle of the second epoch, then Ctrl-C in the middle
# of the third epoch of the run resumed from it: (callback, global step, exit code).
STOPS = [("SigtermAt", STEPS_PER_EPOCH + 7, 143), ("InterruptAt", 2 * STEPS_PER_EPOCH + 7, 130)]


@pytest.fixture(scope="module")
def interrupted_run(tmp_path_factory) -> dict:
    """A 3-epoch train.py fit stopped at each of :data:`STOPS` and resumed with the command it printed, then resumed
    once more when finished and tested (`test --ckpt_path last`): one train.py process per step (each start-up
    imports torch and Lightning: seconds), shared by the interruption test and the no-warning test. Returns
    {"run", "last", "stopped": [(process, global step in last.ckpt, versions) per stop], "resume_args": [the printed
    resume command's arguments per stop], "resumed", "after": the run as the last resume left it (versions, global
    step, recording parts, (ids, steps) of the recording, whether metrics.json exists), "finished", "tested"}."""
    tmp_path = tmp_path_factory.mktemp("interrupted")
    callbacks = [{"class_path": f"fault_injection.{name}", "init_args": {"step": step}} for name, step, _ in STOPS]
    config = write_run_config(tmp_path, epochs=3, callbacks=callbacks)
    run = tmp_path / "runs" / "smoke" / "version_0"
    last = run / "checkpoints" / "last.ckpt"
    out = {"run": run, "last": last, "stopped": [], "resume_args": []}
    args = ["fit", "--config", str(config)]
    for _ in STOPS:
        stopped = run_train(args, tmp_path)
        step = torch.load(last, weights_only=True)["global_step"] if last.is_file() else None
        out["stopped"].append((stopped, step, runs.versions(tmp_path / "runs" / "smoke")))
        if stopped.returncode not in (130, 143):
            return out                                      # the tests name what went wrong
        args = _resume_command(stopped.stderr)
        out["resume_args"].append(args)
    out["resumed"] = run_train(args, tmp_path)
    out["after"] = {"versions": runs.versions(tmp_path / "runs" / "smoke"), "parts": len(list(run.glob("rerun*.rrd"))),
                    "step": torch.load(last, weights_only=True)["global_step"] if last.is_file() else None,
                    "recording": recording(run), "metrics": (run / "metrics.json").is_file()}
    out["finished"] = run_train(["fit", "--config", str(config), "--ckpt_path", "last"], tmp_path)  # a finished run
    out["tested"] = run_train(["test", "--config", str(config), "--ckpt_path", "last"], tmp_path)
    return out


@pytest.mark.slow            # subprocess trainings: behaviour, not float order; make test runs them once
def test_interrupt_mid_epoch_prints_the_resume_command_and_resume_keeps_the_whole_recording(interrupted_run):
    """SIGTERM, then Ctrl-C in the resumed run: each stop saves last.ckpt at its step and prints the command that
    resumes the same run; the last resume trains to the end, and the run keeps one whole recording."""
    run, last = interrupted_run["run"], interrupted_run["last"]
    for (_, stop_at, code), (stopped, step, versions) in zip(STOPS, interrupted_run["stopped"], strict=True):
        assert stopped.returncode == code, stopped.stderr[-2000:]
        assert step == stop_at
        assert versions == [run]                                    # the same run, not a new one
    for args in interrupted_run["resume_args"]:
        assert args[-2:] == ["--ckpt_path", str(last)] or Path(args[-1]).resolve() == last.resolve()
    resumed, after = interrupted_run["resumed"], interrupted_run["after"]
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert after["versions"] == [run]                                 # the same run, not a new one
    assert after["step"] == 3 * STEPS_PER_EPOCH
    ids, steps = after["recording"]
    assert len(ids) == 1 and after["parts"] == len(STOPS) + 1
    assert steps[0] <= 5 and steps[-1] >= 3 * STEPS_PER_EPOCH - 5
    gaps = [b - a for a, b in zip(steps, steps[1:], strict=False)]
    assert max(gaps) <= 5 + 5, gaps                                    # no hole around the interruptions
    assert after["metrics"]


# ---- what the terminal shows ----------------------------------------------------------------------------

@pytest.mark.slow
def test_a_typo_in_the_robot_file_is_one_line_naming_the_file(tmp_path):
    robot = tmp_path / "typo.yaml"
    robot.write_text((ROOT / "configs/robots/type1.yaml").read_text().replace("length: 0.10", "lenght: 0.10"))
    config = write_run_config(tmp_path, epochs=1)
    proc = run_train(["fit", "--config", str(config), "--data.robot", str(robot)], tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert lines == [f"error: {robot}: segments[0]: got ['lenght'], expected only keys body_radius, "
                      "joint_angles, joint_radii, joints, length, limits, offset, radius, type"]
    assert not (tmp_path / "runs").exists()                     # no run folder for a run that never started


@pytest.mark.slow
def test_a_fit_prints_no_warning_a_user_cannot_act_on(interrupted_run):
    """Every train.py process of the interrupted run (a fresh fit and a resumed one, each stopped; the last resume;
    a finished run resumed; its test): no warning, hint or log line that a user cannot act on."""
    procs = [stopped for stopped, _, _ in interrupted_run["stopped"]]
    procs += [interrupted_run[k] for k in ("resumed", "finished", "tested") if k in interrupted_run]
    assert len(procs) == len(STOPS) + 3, "the interrupted run stopped early: see the interruption test"
    for proc in procs[len(STOPS):]:
        assert proc.returncode == 0, proc.stderr[-2000:]
    for proc in procs:
        text = proc.stdout + proc.stderr
        for noise in ("Warning", "deprecated", "💡", "HINT", "no last checkpoint", "DataLoader 0", "Seed set",
                      "GPU available"):
            assert noise not in text, f"{noise!r} in:\n{text}"
