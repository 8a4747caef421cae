"""The README's "Your own robot" section, run as a user would follow it: its YAML written to a file, its
shell commands run (train.py with a shorter training, the export without AOTInductor), then its Python
doctest — load the model, predict, drive the controller on the export — in the same folder.

The commands run in this process, through the entry functions their ``python train.py`` / ``python -m
dacr_learn.export`` call (each interpreter start-up imports torch and Lightning: seconds); test_runs.py and
test_export.py start those two as subprocesses."""
from __future__ import annotations

import doctest
import re
import shlex

import pytest
from conftest import ROOT, readme_sections

import train
from dacr_learn.cli import export as export_cli
from dacr_learn.console import run_cli

SHORTER = {"train.py": ["--trainer.max_epochs", "3", "--data.n_train", "5000", "--data.n_val", "500",
                        "--data.n_test", "500", "--trainer.enable_progress_bar", "false"],
           "dacr_learn.export": ["--no-aoti"]}
ENTRY = {"train.py": train.run_command_line, "dacr_learn.export": lambda argv: run_cli(export_cli.main, argv)}


def blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.S)


@pytest.mark.slow            # trains and exports in subprocesses: run once per make test
def test_own_robot_section_runs_end_to_end(tmp_path, monkeypatch):
    section = readme_sections()["Your own robot"]
    (yaml_text,), commands, (python_text,) = blocks(section, "yaml"), blocks(section, "bash"), blocks(section, "python")
    (tmp_path / "my_robot.yaml").write_text(yaml_text)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    lines = [line.split("#")[0].strip() for block in commands for line in block.splitlines()]
    lines = [line for line in lines if line]
    assert len(lines) == 2, lines
    monkeypatch.chdir(tmp_path)
    for line in lines:
        words = shlex.split(line)
        assert words[0] == ".venv/bin/python", line
        command = words[1] if words[1] != "-m" else words[2]            # the script, or the module after -m
        args = words[2:] if words[1] != "-m" else words[3:]
        assert ENTRY[command](args + SHORTER[command]) == 0, line
    assert (tmp_path / "runs" / "my_robot" / "version_0" / "checkpoints" / "last.ckpt").is_file()
    test = doctest.DocTestParser().get_doctest(python_text, {}, "README: Your own robot", "README.md", 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 7 and result.failed == 0
