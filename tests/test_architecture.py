"""The package's import graph: no cycle, and physics and algorithms never reach files or
the command line. Every import counts: at module level, inside functions, and under
``TYPE_CHECKING``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"
PACKAGE = SRC / "asynhdr"

LAYERED = ("asynhdr.rig", "asynhdr.panel", "asynhdr.scene", "asynhdr.sensor",
           "asynhdr.simulate", "asynhdr.reconstruct", "asynhdr.calibrate", "asynhdr.segment",
           "asynhdr.metrics", "asynhdr.waveform", "asynhdr.tonemap", "asynhdr.events",
           "asynhdr.source")
"""Physics and algorithm modules (and the Source between them and files)."""


def _modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        parts = list(p.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                base = node.module
                if node.level:  # relative: resolve against the importing package
                    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    base = ".".join([*pkg[: len(pkg) - node.level + 1], node.module])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                           for a in node.names]
            for t in targets:
                if t in mods and t != name:
                    graph[name].add(t)
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return [*stack[stack.index(n):], n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_the_graph_sees_imports_of_every_kind() -> None:
    g = _graph()
    # a module-level import, one inside a function, one from a package's submodule
    assert "asynhdr.events" in g["asynhdr.source"]
    assert "asynhdr.cli.core" in g["asynhdr.cli"]
    assert "asynhdr.io._evt_kernels" in g["asynhdr.io.prophesee"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_import_graph_has_no_cycle() -> None:
    assert _cycle(_graph()) is None


@pytest.mark.parametrize("layer", LAYERED)
def test_physics_and_algorithms_import_neither_io_nor_cli(layer: str) -> None:
    g = _graph()
    mods = [m for m in g if m == layer or m.startswith(layer + ".")]
    assert mods, layer
    for m in mods:
        bad = sorted(t for t in g[m] if t.startswith(("asynhdr.io", "asynhdr.cli")))
        assert not bad, f"{m} imports {bad}"
