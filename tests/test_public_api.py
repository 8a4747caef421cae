"""The public API: the package's re-exports, its version, and the examples users read first
(the README's and the package docstring's) run as doctests, so the front page cannot go stale."""
from __future__ import annotations

import doctest
import subprocess
import sys
from importlib.metadata import version

from conftest import ROOT, readme_sections

import dacr_learn

FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE
OWN_ROBOT = "Your own robot"


def test_version_is_the_installed_distribution_version():
    assert dacr_learn.__version__ == version("dacr_learn")
    out = subprocess.run([sys.executable, "-c", "import dacr_learn; print(dacr_learn.__version__)"],
                         capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == dacr_learn.__version__


def test_all_names_exist_and_are_the_library_objects():
    from dacr_learn.export import load
    from dacr_learn.kinematics import forward_kinematics
    from dacr_learn.robot import RobotSpec

    assert all(hasattr(dacr_learn, name) for name in dacr_learn.__all__)
    assert dacr_learn.RobotSpec is RobotSpec and dacr_learn.forward_kinematics is forward_kinematics
    assert dacr_learn.load_exported is load


def test_package_docstring_example_runs():
    result = doctest.testmod(dacr_learn, optionflags=FLAGS)
    assert result.attempted >= 4 and result.failed == 0


def test_readme_example_runs(monkeypatch, tmp_path):
    # run where a user would, beside configs/, but in a fresh folder: the IK example writes T.npy
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    # every doctest of the README but "Your own robot", which needs a trained run (test_readme_own_robot.py)
    text = "".join(body for name, body in readme_sections().items() if name != OWN_ROBOT)
    test = doctest.DocTestParser().get_doctest(text, {}, "README.md", str(ROOT / "README.md"), 0)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 8 and result.failed == 0
