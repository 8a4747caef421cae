"""The README's "Your own robot" section, run as a user would follow it: its YAML written to a file, its
shell commands run (train.py with a shorter training, the export without AOTInductor), then its Python
doctest — load the model, predict, drive the controller on the export — in the same folder."""
from __future__ import annotations

import doctest
import re
import shlex
import subprocess
import sys

import pytest
from conftest import ROOT, readme_sections

SHORTER = {"train.py": ["--trainer.max_epochs", "3", "--data.n_train", "5000", "--data.n_val", "500",
                        "--data.n_test", "500", "--trainer.enable_progress_bar", "false"],
           "dacr_learn.export": ["--no-aoti"]}


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
    for line in lines:
        words = shlex.split(line)
        assert words[0] == ".venv/bin/python", line
        words = [sys.executable] + [str(ROOT / w) if w == "train.py" else w for w in words[1:]]
        words += next(extra for key, extra in SHORTER.items() if key in line)
        proc = subprocess.run(words, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{line}\n{proc.stderr[-3000:]}"
    assert (tmp_path / "runs" / "my_robot" / "version_0" / "checkpoints" / "last.ckpt").is_file()
    monkeypatch.chdir(tmp_path)
    test = doctest.DocTestParser().get_doctest(python_text, {}, "README: Your own robot", "README.md", 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 7 and result.failed == 0
