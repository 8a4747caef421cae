"""The README's way to make a targets file for the IK CLI, run as a user would follow it: its Python snippet
(sample features inside the limits, their tip poses, ``np.save``) in a fresh folder, then the CLI command of the
same section on the file it wrote (its ``python -m`` entry, run in this process); every target is reachable, so
every slot must come back solved."""
from __future__ import annotations

import doctest
import re
import runpy
import shlex
import sys

import numpy as np
from conftest import ROOT, readme_sections


def test_readme_targets_snippet_feeds_the_ik_cli(tmp_path, monkeypatch, capsys):
    section = next(body for name, body in readme_sections().items() if name.startswith("Inverse kinematics"))
    (snippet,) = [b for b in re.findall(r"```python\n(.*?)```", section, flags=re.S) if "np.save" in b]
    (command,) = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    test = doctest.DocTestParser().get_doctest(snippet, {}, "README: IK targets", "README.md", 0)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    runner.run(test)
    assert runner.summarize(verbose=False).failed == 0
    targets = np.load(tmp_path / "T.npy")
    assert targets.dtype == np.float64 and targets.shape == (100, 4, 4)

    words = shlex.split(command.strip())
    assert words[:3] == [".venv/bin/python", "-m", "dacr_learn.ik"], command
    words[words.index("--solutions") + 1] = "2"              # the README asks for 8; 2 keep the test fast
    monkeypatch.setattr(sys, "argv", ["python -m dacr_learn.ik", *words[3:]])
    try:                                                     # the `python -m` entry, in this process
        runpy.run_module("dacr_learn.ik", run_name="__main__", alter_sys=True)
    except SystemExit as exited:
        assert exited.code in (0, None), capsys.readouterr().err[-3000:]
    with np.load(tmp_path / "S.npz") as out:
        assert out["q"].shape == (100, 2, 12) and out["success"].all()
