"""The package's shape, read from its source (ast): no import cycles, no module reaching for another
module's private names, no file over 400 lines, and the layers of the hardware wing depending only
downward (core ← deploy ← study).

Every ``import`` statement counts, also those inside functions (a lazy import still ties two modules
together); the implicit import of a parent package is not an edge.
"""
from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

PACKAGE = ROOT / "dacr_learn"
MAX_LINES = 400


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def resolve(importer: str, is_package: bool, level: int, target: str | None) -> str:
    """Absolute module name of a (possibly relative) import in module ``importer``."""
    if level == 0:
        return target or ""
    base = importer.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def imports(name: str, path: Path, known: dict[str, Path]) -> list[tuple[str, str | None, int]]:
    """(imported module, imported private name or None, line) of every import in a module of ours."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, None, node.lineno) for a in node.names if a.name.startswith("dacr_learn")]
        elif isinstance(node, ast.ImportFrom):
            source = resolve(name, is_package, node.level, node.module)
            if not source.startswith("dacr_learn"):
                continue
            for alias in node.names:
                child = f"{source}.{alias.name}"
                if child in known:                       # `from . import export`: the submodule itself
                    found.append((child, None, node.lineno))
                else:
                    private = alias.name if alias.name.startswith("_") and not alias.name.startswith("__") else None
                    found.append((source, private, node.lineno))
    return found


def module_aliases(name: str, path: Path, known: dict[str, Path]) -> dict[str, str]:
    """Local name → module of ours bound by `import … as x` / `from … import module as x`."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    aliases = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            source = resolve(name, path.name == "__init__.py", node.level, node.module)
            for alias in node.names:
                if f"{source}.{alias.name}" in known:
                    aliases[alias.asname or alias.name] = f"{source}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known and alias.asname:
                    aliases[alias.asname] = alias.name
    return aliases


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: {m for m, _, _ in imports(name, path, known) if m in known and m != name}
            for name, path in known.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_the_checker_finds_a_cycle_and_a_private_import(tmp_path):
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    code = tmp_path / "m.py"
    code.write_text("from .kinematics import _chain, forward_kinematics\nfrom . import export\n")
    known = {"dacr_learn.kinematics": code, "dacr_learn.export": code, "dacr_learn.m": code}
    found = imports("dacr_learn.m", code, known)
    assert ("dacr_learn.kinematics", "_chain", 1) in found and ("dacr_learn.export", None, 2) in found


def test_no_import_cycles():
    assert cycles(graph()) == []


def test_no_module_imports_another_modules_private_names():
    known = modules()
    offences = []
    for name, path in known.items():
        offences += [f"{name}:{line} imports {private} from {source}"
                     for source, private, line in imports(name, path, known) if private and source != name]
        aliases = module_aliases(name, path, known)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                offences.append(f"{name}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
    assert offences == []


def test_no_file_in_the_package_is_over_400_lines():
    long = {str(p.relative_to(ROOT)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert long == {}


def test_the_synthetic_export_imports_nothing_of_hardware():
    edges = graph()
    assert not {m for m in edges["dacr_learn.export"] if m.startswith("dacr_learn.hardware")}


def test_hardware_layers_depend_only_downward():
    """dacr_learn.hardware (data, physics, models) ← .deploy (checkpoints, inference, export) ← .study
    (model registry, selection, benchmark, CLI): a lower layer imports nothing of a higher one."""
    rank = {"dacr_learn.hardware.study": 2, "dacr_learn.hardware.deploy": 1}

    def layer(module: str) -> int:
        return next((r for prefix, r in rank.items() if module == prefix or module.startswith(prefix + ".")),
                    0 if module.startswith("dacr_learn.hardware") else -1)

    upward = [f"{a} → {b}" for a, targets in graph().items() for b in targets
              if layer(a) >= 0 and layer(b) > layer(a) and a != "dacr_learn.hardware.__main__"]
    assert upward == []
