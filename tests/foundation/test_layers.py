"""Layers are one-way: no module imports from a layer above its own, and the import graph has no cycle.

Every import of every ``tnf`` module counts (module level and inside functions; relative ones resolved).
Layers, lowest first, are in ``LAYERS`` (the README's "Where things are" lists them).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import tnf

ROOT = Path(tnf.__file__).parent

# Lowest first. A module's layer is its first match: a package name, or a core module's dotted name.
LAYERS: list[tuple[str, ...]] = [
    (
        "tnf",
        "tnf.errors",
        "tnf.settings",
        "tnf.registry",
        "tnf.artifacts",
        "tnf.env",
        "tnf.runtime",
        "tnf.listing",
        "tnf.cameras",
        "tnf.metrics",
        "tnf.sensors",
        "tnf.touches",
    ),
    ("tnf.objects",),
    ("tnf.capture",),
    ("tnf.scenes",),
    ("tnf.sim",),
    ("tnf.data",),
    ("tnf.generators",),
    ("tnf.eval", "tnf.real"),
    ("tnf.testing",),
    ("tnf.stages",),
    ("tnf.cli",),
]


def module_name(path: Path) -> str:
    parts = ("tnf",) + path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def layer_of(name: str) -> int:
    best, best_len = -1, -1
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > best_len and (p != "tnf" or name == "tnf"):
                best, best_len = i, len(p)
    if best < 0:
        raise AssertionError(f"module {name} is in no layer; add it to LAYERS in {__file__}")
    return best


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """Every tnf module that ``name`` imports, anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # `from pkg import sub` imports the submodule pkg.sub where one exists.
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t.startswith("tnf") and t != name:
                found.add(t)
    return found


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: imports_of(name, path, set(mods)) for name, path in mods.items()}


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def upward_imports(edges: dict[str, set[str]]) -> list[str]:
    bad = []
    for src, dsts in sorted(edges.items()):
        for dst in sorted(dsts):
            if layer_of(dst) > layer_of(src):
                bad.append(f"{src} (layer {layer_of(src)}) imports {dst} (layer {layer_of(dst)})")
    return bad


def test_every_module_has_a_layer() -> None:
    for name in modules():
        layer_of(name)


def test_no_module_imports_from_a_layer_above() -> None:
    bad = upward_imports(graph())
    assert not bad, "imports from a layer above:\n" + "\n".join(bad)


def test_import_graph_has_no_cycle() -> None:
    cycle = find_cycle(graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_checks_catch_a_cycle_and_an_upward_import() -> None:
    edges = {"tnf.objects.a": {"tnf.capture"}, "tnf.capture": {"tnf.objects.a"}}
    assert find_cycle(edges) == ["tnf.capture", "tnf.objects.a", "tnf.capture"]
    assert upward_imports(edges) == ["tnf.objects.a (layer 1) imports tnf.capture (layer 2)"]


@pytest.mark.parametrize(
    ("src", "level", "mod", "expected"),
    [("tnf.scenes.fit", 1, "system", "tnf.scenes.system"), ("tnf.scenes", 1, "fit", "tnf.scenes.fit")],
)
def test_relative_imports_resolve(tmp_path: Path, src: str, level: int, mod: str, expected: str) -> None:
    path = tmp_path / ("__init__.py" if src == "tnf.scenes" else "fit.py")
    path.write_text(f"from {'.' * level}{mod} import x\n")
    assert imports_of(src, path, set(modules())) == {expected}
