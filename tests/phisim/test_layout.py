"""The package's structure as tested invariants: layers import only lower layers, no import circles, no imports
of another module's private names, no imports hidden inside functions, old module paths still import."""

from __future__ import annotations

import ast
import importlib
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "phisim"

#: The layers, lowest first; a module may import its own layer and the ones before it.
LAYERS = ["core", "spectral", "ops", "solvers", "fluid", "pde", "io", "viz", "simulate"]
#: Where lazy imports inside functions are allowed: optional or heavy dependencies behind a public name.
LAZY_ALLOWED = {("phisim/__init__.py", "phisim.viz")}  # matplotlib only when a plot function is first used


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else "core"


def _imports(path: Path):
    """``(imported module, names, at module level?)`` for every phisim import of a file."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    guarded = set()  # imports under ``if TYPE_CHECKING:`` at module level count as module level
    for node in tree.body:
        if isinstance(node, ast.If):
            guarded |= {id(n) for n in ast.walk(node)}
    this = _module_name(path)
    package = this if path.name == "__init__.py" else this.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "phisim":
                continue
            names = [a.name for a in node.names]
            # ``from phisim.x import y`` where y is a submodule imports phisim.x.y (the package phisim.x is only
            # the way there); other names come from phisim.x itself
            subs = [f"{mod}.{n}" for n in names
                    if (PKG.parent / f"{mod}.{n}".replace(".", "/")).with_suffix(".py").exists()
                    or (PKG.parent / f"{mod}.{n}".replace(".", "/") / "__init__.py").exists()]
            targets = subs + ([mod] if len(subs) < len(names) else [])
            for t in targets:
                yield t, names, id(node) in top or id(node) in guarded
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "phisim":
                    yield a.name, [], id(node) in top or id(node) in guarded


FILES = sorted(p for p in PKG.rglob("*.py"))


def test_layers_import_only_lower_layers():
    bad = []
    for path in FILES:
        this = _module_name(path)
        if this == "phisim" or this == "phisim.compat":  # the package re-exports every layer
            continue
        mine = LAYERS.index(_layer(this))
        for mod, _, _ in _imports(path):
            other = _layer(mod) if mod != "phisim" else "core"
            if LAYERS.index(other) > mine:
                bad.append(f"{this} ({_layer(this)}) imports {mod} ({other})")
    assert not bad, "\n".join(bad)


def test_no_import_circles():
    graph: dict[str, set[str]] = {}
    for path in FILES:
        this = _module_name(path)
        graph[this] = {m for m, _, _ in _imports(path) if m != this and m in {_module_name(p) for p in FILES}}
    # a package's __init__ imports its modules; modules importing their own package's public names would close
    # a circle through the __init__: report those too
    state: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                circles.append(stack[stack.index(m):] + [m])
            elif m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 5000))
    for n in sorted(graph):
        if n not in state:
            visit(n)
    assert not circles, "\n".join(" -> ".join(c) for c in circles)


def test_no_private_names_from_other_modules():
    bad = []
    for path in FILES:
        this = _module_name(path)
        for mod, names, _ in _imports(path):
            for n in names:
                if n.startswith("_") and mod != this:
                    bad.append(f"{this}: from {mod} import {n}")
    assert not bad, "\n".join(bad)


def test_no_imports_inside_functions():
    bad = []
    for path in FILES:
        rel = str(path.relative_to(ROOT))
        for mod, _, top in _imports(path):
            if not top and (rel, mod) not in LAZY_ALLOWED:
                bad.append(f"{rel}: {mod} imported inside a function")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("old", sorted(importlib.import_module("phisim.compat").MOVED))
def test_old_module_paths_import_the_new_modules_with_a_warning(old):
    from phisim.compat import MOVED

    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    assert module is importlib.import_module(MOVED[old])
    assert any(issubclass(w.category, DeprecationWarning) and MOVED[old] in str(w.message) for w in caught)
