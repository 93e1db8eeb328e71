"""The house rules of the code: no import cycles anywhere, ``sfm``'s layers import downwards only
(the order stated in the ``sfm`` package docstring), and ``graph/`` and ``backend/`` are array
libraries that import neither ``sfm`` nor each other."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import networkx as nx

import sfm

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sfm", "graph", "backend")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules that ``path`` imports anywhere in its body (functions and
    TYPE_CHECKING blocks included); ``from a.b import c`` counts ``a.b.c`` when it is a module."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out.update(n for n in names if n in modules)
    return out


def _graph() -> nx.DiGraph:
    modules = _modules()
    g = nx.DiGraph()
    for name, path in modules.items():
        g.add_node(name)
        for target in _imports(path, modules):
            if target != name and not name.startswith(target + "."):  # a package's own __init__
                g.add_edge(name, target)
    return g


def layers_from_docstring() -> dict[str, int]:
    """``{unit: layer}`` from the numbered layer list of the ``sfm`` package docstring."""
    layers = {}
    for number, units in re.findall(r"^\s*(\d+)\.\s+(sfm\.[\w., ]+)$", sfm.__doc__ or "", flags=re.M):
        for unit in units.split(","):
            layers[unit.strip()] = int(number)
    return layers


def _unit(module: str, layers: dict[str, int]) -> str | None:
    parts = module.split(".")
    for k in (2, 1):
        if ".".join(parts[:k]) in layers:
            return ".".join(parts[:k])
    return None


def test_no_import_cycles():
    cycles = list(nx.simple_cycles(_graph()))
    assert not cycles, f"import cycles: {cycles[:5]}"


def test_graph_and_backend_are_array_libraries():
    bad = [(a, b) for a, b in _graph().edges
           if (a.startswith("graph") and not b.startswith("graph"))
           or (a.startswith("backend") and not b.startswith("backend"))]
    assert not bad, bad


def upward_imports(edges, layers: dict[str, int]) -> list[str]:
    """The imports between two different units of ``sfm`` that do not go to a lower layer."""
    upward = []
    for a, b in edges:
        if not (a.startswith("sfm.") and b.startswith("sfm.")):
            continue
        ua, ub = _unit(a, layers), _unit(b, layers)
        if ua != ub and layers[ub] >= layers[ua]:
            upward.append(f"{a} -> {b} (layer {layers[ua]} -> {layers[ub]})")
    return upward


def test_sfm_layers_import_downwards_only():
    layers = layers_from_docstring()
    assert len(layers) >= 10 and "sfm.core" in layers and "sfm.cli" in layers
    modules = [m for m in _modules() if m.startswith("sfm.")]
    unplaced = [m for m in modules if _unit(m, layers) is None]
    assert not unplaced, f"modules in no layer of the sfm docstring: {unplaced}"
    upward = upward_imports(_graph().edges, layers)
    assert not upward, "imports that do not go down: " + "; ".join(upward)


def test_the_layer_rule_flags_upward_and_sideways_imports_only():
    layers = {"sfm.core": 0, "sfm.io": 1, "sfm.viz": 1, "sfm.cli": 2}
    edges = [("sfm.io.database", "sfm.core.model"),  # down: fine
             ("sfm.io.database", "sfm.io.workspace"),  # within a unit: fine
             ("sfm.core.model", "sfm.io.database"),  # up
             ("sfm.io.database", "sfm.viz.recorder"),  # sideways, same layer
             ("sfm.cli", "sfm.core.options")]  # a top-level module, down: fine
    assert upward_imports(edges, layers) == ["sfm.core.model -> sfm.io.database (layer 0 -> 1)",
                                             "sfm.io.database -> sfm.viz.recorder (layer 1 -> 1)"]
