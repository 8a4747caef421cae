"""Every research script still imports against the library (research/ is imported by nothing else).

The scripts are frozen (research/__init__.py): running them takes minutes to hours, so only their imports
are checked here: a renamed or removed library name they use fails this test instead of the next person
who reruns a figure. Importing runs no script: each guards its work with ``if __name__ == "__main__"``.
"""
from __future__ import annotations

import importlib

import pytest
from conftest import ROOT

MODULES = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
                 for p in (ROOT / "research").rglob("*.py"))


def test_the_research_package_has_scripts():
    assert "research.hardware_cv.common" in MODULES and len(MODULES) > 30


@pytest.mark.parametrize("name", MODULES)
def test_research_module_imports(name):
    importlib.import_module(name)
