"""The package's shape, read from its source (ast): no import cycles, no module reaching for another
module's private names, no file over 400 lines, and the layers (:data:`LAYERS`: core maths ← physics ← data ←
learning, viz ← deploy ← hardware ← hardware.deploy ← hardware.study ← entry points) depending only downward,
with Lightning and Rerun only where they belong.

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


# Every module of the package belongs to one layer (the first whose prefixes match it, longest prefix first);
# a module imports only modules of its own layer or of layers listed before it.
LAYERS = {
    "core": ["checks", "console", "robot", "clarke", "layers", "component_algebra", "lie", "kinematics", "metrics",
             "models", "folding", "compositional", "limits", "clarke_space", "sampler", "body", "scene"],
    "physics": ["cosserat"],
    "data": ["data"],
    "learning": ["datamodule", "training", "training_sampler", "runs", "ablation", "combination_shift"],
    "viz": ["viz"],
    "deploy": ["deploy", "ik", "arm", "plan"],
    "hardware": ["hardware"],
    "hardware.deploy": ["hardware.deploy"],
    "hardware.study": ["hardware.study"],
    # the root, the command lines (cli) and the thin `python -m dacr_learn.<package>` shims that run them
    "entry": ["", "export", "cli", "hardware.__main__", "ablation.__main__", "ik.__main__", "ik.exported.__main__",
              "arm.exported.__main__",
              "plan.__main__"],
}
NO_LIGHTNING_OR_RERUN = ("core", "physics", "data", "deploy", "hardware", "hardware.deploy")


def layer_of(module: str) -> str:
    """The layer of a module of ours (ValueError for one that no layer claims)."""
    rel = module.removeprefix("dacr_learn").removeprefix(".")
    matches = [(len(p), name) for name, prefixes in LAYERS.items() for p in prefixes
               if rel == p or (p and rel.startswith(p + "."))]
    if not matches:
        raise ValueError(f"{module}: no layer in LAYERS claims it; add it where it belongs")
    return max(matches)[1]


def test_every_module_has_a_layer_and_the_checker_sees_an_upward_import():
    assert [layer_of(m) for m in ("dacr_learn", "dacr_learn.lie", "dacr_learn.data.cosserat", "dacr_learn.deploy",
                                  "dacr_learn.hardware.deploy.export", "dacr_learn.hardware.study.benchmark",
                                  "dacr_learn.export", "dacr_learn.hardware.__main__", "dacr_learn.cli.ik",
                                  "dacr_learn.ik.exported", "dacr_learn.ik.exported.__main__")] == [
        "entry", "core", "data", "deploy", "hardware.deploy", "hardware.study", "entry", "entry", "entry", "deploy",
        "entry"]
    order = list(LAYERS)
    assert order.index(layer_of("dacr_learn.deploy.export")) > order.index(layer_of("dacr_learn.runs"))
    unclaimed = []
    for m in modules():
        try:
            layer_of(m)
        except ValueError as err:
            unclaimed.append(str(err))
    assert unclaimed == []


def test_layers_depend_only_downward():
    order = list(LAYERS)
    upward = [f"{a} ({layer_of(a)}) → {b} ({layer_of(b)})" for a, targets in graph().items() for b in targets
              if order.index(layer_of(b)) > order.index(layer_of(a))]
    assert upward == []


def test_the_maths_deploy_and_hardware_import_no_lightning_or_rerun():
    found = []
    for name, path in modules().items():
        if layer_of(name) not in NO_LIGHTNING_OR_RERUN:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            roots = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            found += [f"{name}:{node.lineno} imports {r}" for r in roots
                      if r.split(".")[0] in ("lightning", "pytorch_lightning", "rerun")]
    assert found == []


def test_the_synthetic_deploy_layer_imports_nothing_of_hardware():
    edges = graph()
    assert not {f"{a} → {b}" for a, targets in edges.items() if layer_of(a) == "deploy"
                for b in targets if b.startswith("dacr_learn.hardware")}


def test_the_solver_imports_neither_the_arm_nor_the_hardware():
    """ik/ is below arm/ and hardware/ (both build on it): no module under dacr_learn/ik imports either, also not a
    command line living there (they are in cli/)."""
    solver = [a for a in graph() if a.split(".")[:2] == ["dacr_learn", "ik"]]
    assert len(solver) > 5
    assert sorted(f"{a} → {b}" for a in solver for b in graph()[a] if b.split(".")[1] in ("arm", "hardware")) == []


def test_only_the_command_lines_and_their_shims_import_cli():
    edges = graph()
    assert sorted(f"{a} → {b}" for a, targets in edges.items() for b in targets
                  if b.startswith("dacr_learn.cli") and not a.startswith("dacr_learn.cli")
                  and not a.endswith(".__main__")) == []
