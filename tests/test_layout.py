"""The package's layout: imports run one way (../shared/STYLE.md, "Dependency direction").

command line -> readers of results (figures, outputs, benchmark) -> pipeline steps -> the model
of the world and the backends; backends -> model only. Lazy imports inside functions count.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "fsswarp"

MODEL = {"errors", "atomic", "caching", "system", "processes", "sonar", "rig", "surface", "targets", "dataset", "scenes", "metrics"}
PIPELINE = {"aris", "segment", "icp", "motion", "compare", "rendering", "simulation", "carving", "pose", "refine",
            "reconstruction", "enhancement", "didson", "importing", "holoocean"}
READERS = {"figures", "outputs", "benchmark"}
TOP = {"cli", "__main__", "batch", "report", "resident"}
#: What each layer may import besides itself.
ALLOWED = {"model": {"model"}, "backends": {"model", "backends"}, "pipeline": {"model", "backends", "pipeline"},
           "readers": {"model", "backends", "pipeline", "readers"},
           "top": {"model", "backends", "pipeline", "readers", "top"}}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def layer(module: str) -> str:
    if module == "fsswarp":
        return "top"
    first = module.split(".")[1]
    for name, members in (("model", MODEL), ("pipeline", PIPELINE), ("readers", READERS), ("top", TOP)):
        if first in members:
            return name
    if first == "backends":
        return "backends"
    raise AssertionError(f"{module} belongs to no layer: add it to one in tests/test_layout.py")


def imports(module: str) -> set[str]:
    """The fsswarp modules ``module`` imports, at the top or inside functions."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            candidates = [f"{target}.{alias.name}" for alias in node.names] + [target]
            found.update(next(([c] for c in candidates if c in MODULES), []))
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name in MODULES)
    found.discard(module)
    return found


GRAPH = {module: imports(module) for module in MODULES}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_one_way(module):
    mine = layer(module)
    wrong = sorted(m for m in GRAPH[module] if m != "fsswarp" and layer(m) not in ALLOWED[mine])
    assert not wrong, f"{module} ({mine}) imports {wrong}"
    assert "fsswarp" not in GRAPH[module] or module == "fsswarp.__main__", f"{module} imports the package itself"


def test_no_import_cycle():
    """Tarjan's strongly connected components: every one is a single module."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_public_api_is_reexported_without_shadowing_a_module():
    import fsswarp

    for name in fsswarp.__all__:
        assert callable(getattr(fsswarp, name)), name
        assert f"fsswarp.{name}" not in MODULES, f"fsswarp.{name} is both a function and a module"
    for module in sorted(set(MODULES) - {"fsswarp.__main__"}):  # __main__ runs the command line
        importlib.import_module(module)
