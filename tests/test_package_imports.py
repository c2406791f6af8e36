"""The package's import graph: benchmarks stay out of the algorithms, and no module cycle.

Every `import` and `from ... import` of dmais_pipe's modules is read with `ast` (those inside
functions too, which a run-time check would only see when the function runs), resolved to the
module it names, and checked; a subprocess also imports the algorithm packages and lists what
came with them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dmais_pipe"
ALGORITHMS = ("markers", "pose", "calib", "sim")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """The dmais_pipe modules (dotted names) that the module at path imports anywhere in it."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")
            base = base[:len(base) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            # `from . import xfit` imports the module xfit; `from .refine import seed` the module refine
            found |= {f"{target}.{alias.name}" for alias in node.names} | {target}
    modules = _all_modules()
    return {m for m in found if m in modules and m != name}


def _all_modules() -> set[str]:
    return {_module_name(p) for p in PACKAGE.rglob("*.py")}


def _graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def test_no_algorithm_module_imports_the_benchmarks():
    graph = _graph()
    algorithms = {m: imports for m, imports in graph.items() if m.split(".")[1:2] and m.split(".")[1] in ALGORITHMS}
    assert len(algorithms) > 30
    offenders = {m: sorted(i for i in imports if i.startswith("dmais_pipe.bench")) for m, imports in algorithms.items()}
    assert {m: i for m, i in offenders.items() if i} == {}
    assert {m for m in graph if m.startswith(("dmais_pipe.markers.bench", "dmais_pipe.pose.bench"))} == set()
    assert "dmais_pipe.bench.markers" in graph and "dmais_pipe.bench.pose" in graph


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle among modules (a list of names, first == last), or [] where there is none."""
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return []

    for start in sorted(graph):
        if start not in state and (found := visit(start)):
            return found
    return []


def test_module_cycle_finder_finds_a_planted_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) == []


@pytest.mark.parametrize("package", ["dmais_pipe.markers", "dmais_pipe.pose", "dmais_pipe.bench"])
def test_no_import_cycle_between_modules_of(package):
    graph = _graph()
    # a package's __init__ imports its modules by design; a cycle through it is not one of theirs
    inside = {m: {i for i in imports if i.startswith(package + ".")} for m, imports in graph.items()
              if m.startswith(package + ".")}
    assert _cycle(inside) == []


def test_importing_the_algorithms_loads_no_benchmark():
    code = ("import sys, dmais_pipe.markers, dmais_pipe.pose, dmais_pipe.markers.shadow, dmais_pipe.markers.refine; "
            "print(sorted(m for m in sys.modules if m.startswith('dmais_pipe')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "dmais_pipe.markers.refine" in loaded and "dmais_pipe.pose.solver" in loaded
    assert "dmais_pipe.bench" not in loaded
