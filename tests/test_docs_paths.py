"""The user's guide names only what exists and speaks of the project: every ``dacr_learn/…`` path (and every path
under tests/, benchmarks/, examples/, configs/, research/) and every ``python -m …`` module named in README.md and
docs/*.md is in the repository; every relative link of those pages and of docs/history/ resolves (file and
``#anchor``); design.md's architecture names every layer of tests/test_structure.py and every package; and no page
of the guide, of the research record (docs/history/) or of CHANGELOG.md talks about who ran something or cites an
internal issue number: they speak of the machine, the command, the date and the figure."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import ROOT
from test_structure import LAYERS

GUIDE = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
HISTORY = sorted((ROOT / "docs" / "history").glob("*.md"))
CHANGELOG = ROOT / "CHANGELOG.md"

PATH = re.compile(r"(?<![\w/.])(?:dacr_learn|tests|benchmarks|examples|configs|research)/[\w./-]*")
MODULE = re.compile(r"python -m ([A-Za-z_][\w.]*)")
LINK = re.compile(r"\]\(([^)\s]+)\)")
WHO = re.compile(r"\b(agents?|helpers?|this session|sessions?|the lead|(?:we|I) (?:ran|measured|evaluated|tried)|"
                 r"our (?:reading|criterion))\b|\bwe did\b", re.I)
ISSUE = re.compile(r"\bissues?(?:'s)?\s+#?\d+|(?<![\w&/])#\d+\b(?!-)"      # #2026-11-23-… is a dated heading's anchor
                   r"|\b(?:on|in) the issue\b|\bthe issue's\b|\(issue\)", re.I)
OUTSIDE = {"pytest", "pip", "venv", "torch", "http.server"}     # modules of the environment, not of the repo


def text(page: Path) -> str:
    return page.read_text(encoding="utf-8")


def module_file(name: str) -> Path | None:
    """The file ``python -m name`` runs in this repository: a package's ``__main__.py`` or a module that has a
    ``__main__`` block; None if there is none."""
    base = ROOT.joinpath(*name.split("."))
    if (base / "__main__.py").is_file():
        return base / "__main__.py"
    module = base.with_suffix(".py")
    if module.is_file() and "__name__ == \"__main__\"" in text(module):
        return module
    return None


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces → hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    found, seen, fence = set(), {}, False
    for line in text(page).splitlines():
        fence ^= line.startswith("```")
        if not fence and (m := re.match(r"#{1,6} (.*)", line)):
            s = slug(m.group(1))
            found.add(s if s not in seen else f"{s}-{seen[s]}")
            seen[s] = seen.get(s, 0) + 1
    return found


def exists(path: str) -> bool:
    """A named path is in the repository; one ending in ``_`` names a family of files (``configs/robots/hetero_*``)."""
    path = path.rstrip(".")
    if path.endswith("_"):
        return any((ROOT / path).parent.glob(Path(path).name + "*"))
    return (ROOT / path).exists()


def test_the_checkers_see_what_they_should():
    assert PATH.findall("see `dacr_learn/ik/cli.py`, runs/dacr_learn/x and tests/test_ik.py.") == [
        "dacr_learn/ik/cli.py", "tests/test_ik.py."]
    assert exists("tests/test_ik.py.") and exists("configs/robots/hetero_") and not exists("tests/test_errata.py")
    assert MODULE.findall(".venv/bin/python -m dacr_learn.ik --robot x") == ["dacr_learn.ik"]
    assert module_file("dacr_learn.ik") is not None and module_file("dacr_learn.kinematics") is None
    assert slug("## 1. The joint-space abstraction (`robot.py`, `clarke.py`)".lstrip("# ")) == \
        "1-the-joint-space-abstraction-robotpy-clarkepy"
    assert WHO.search("two other Agents' jobs") and WHO.search("this session") and not WHO.search("sessionless")
    assert WHO.search("for the lead's quiet run") and WHO.search("I evaluated it") and WHO.search("we did not test")
    assert not WHO.search("leads with") and not WHO.search("I + ξ^ + fξ^²")
    assert ISSUE.search("(issue 30, item 3)") and ISSUE.search("see #32") and not ISSUE.search("[x](#results)")
    assert ISSUE.search("(#32)") and not ISSUE.search("[Deploying (j)](#2026-11-23-deploying-the-model)")
    assert ISSUE.search("after issues 21–23's work") and ISSUE.search("reported on the issue")
    assert not ISSUE.search("a float32 issue is excluded") and not ISSUE.search("[§10](cosserat.md#10-displacement)")


@pytest.mark.parametrize("page", GUIDE, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_named_path_and_module_exists(page):
    missing = [p for p in PATH.findall(text(page)) if not exists(p)]
    missing += [f"python -m {m}" for m in MODULE.findall(text(page))
                if m.split(".")[0] not in OUTSIDE and module_file(m) is None]
    assert missing == [], f"{page.name} names what the repository does not have"


@pytest.mark.parametrize("page", GUIDE + HISTORY, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in LINK.findall(text(page)):
        if re.match(r"[a-z]+:", target):                 # http(s):, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(target)
    assert broken == [], f"{page.name}: links to what is not there"


@pytest.mark.parametrize("page", GUIDE + HISTORY + [CHANGELOG], ids=lambda p: str(p.relative_to(ROOT)))
def test_every_page_speaks_of_the_project(page):
    lines = [f"{i}: {line.strip()}" for i, line in enumerate(text(page).splitlines(), 1)
             if WHO.search(line) or ISSUE.search(line)]
    assert lines == [], f"{page.name}: who ran it or an internal issue number"


def test_the_guide_fits_an_afternoon():
    lines = sum(len(text(p).splitlines()) for p in GUIDE if p.parent.name == "docs")
    assert lines <= 2600, f"docs/*.md (outside docs/history/) has {lines} lines; the guide's budget is 2,600"


def test_design_draws_the_layers_the_structure_test_enforces():
    design = text(ROOT / "docs" / "design.md")
    section = design[design.index("## 5. Architecture"):design.index("## 6.")]
    rows = re.findall(r"^\| ([\w.]+) \|", section, flags=re.M)
    assert [r for r in rows if r != "layer"] == list(LAYERS)
    packages = sorted(p.parent.relative_to(ROOT / "dacr_learn").as_posix()
                      for p in (ROOT / "dacr_learn").rglob("__init__.py") if p.parent != ROOT / "dacr_learn")
    assert [p for p in packages if f"{p.split('/')[-1]}/" not in section] == []
