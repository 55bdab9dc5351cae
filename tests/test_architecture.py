"""The layers the folders show (ARCHITECTURE.md), held against the code's own imports.

Every ``import`` in the package counts, module-level or inside a function. A
module may import its own package and the layers below; OpenCascade (OCP,
build123d) only in the bridge; processes only in the runner's executors
(``run/executor.py``, and the Dask cluster in ``run/cluster.py``); and no
import cycle between modules.
"""
from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "bonecad"

#: low to high; a module may import modules of its own group or of lower ones
LAYERS: list[tuple[str, ...]] = [
    ("bonecad._version", "bonecad.errors", "bonecad.staging", "bonecad.settings"),  # base: one group
    ("bonecad.splines",),                                   # spline kernel: numpy/scipy
    ("bonecad.mesh",),                                      # triangle meshes (bone, tessellations)
    ("bonecad.occ",),                                       # the OpenCascade bridge
    ("bonecad.imaging", "bonecad.anatomy"),                 # stages: CT -> mesh, anatomical frame
    ("bonecad.contours",),                                  # stage: contour curves
    ("bonecad.nurbs_model", "bonecad.tspline_model"),       # stages: the two models
    ("bonecad.analysis", "bonecad.fe"),                     # stages: deviation, continuity; FE arrays
    ("bonecad.render", "bonecad.export"),                   # edge: figures, files
    ("bonecad.run",),                                       # edge: runner, executors, CLI
    ("bonecad",),                                           # the package's face (__init__)
]
BASE = LAYERS[0]


def _module(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(path: Path) -> tuple[set[str], set[str]]:
    """(bonecad modules, other top-level modules) that a file imports anywhere."""
    own, other = set(), set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                (own if alias.name.split(".")[0] == "bonecad" else other).add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import"
            base = node.module or ""
            if base.split(".")[0] != "bonecad":
                other.add(base)
                continue
            for alias in node.names:
                full = f"{base}.{alias.name}"
                own.add(full if full in MODULES else base)
    return own, {name.split(".")[0] for name in other}


IMPORTS = {name: _imports(path) for name, path in MODULES.items()}


def _group(module: str) -> tuple[int, str]:
    """(layer index, group) of a module: its package at the layer's depth; the base is one group."""
    best = max(((i, g) for i, groups in enumerate(LAYERS) for g in groups
                if module == g or module.startswith(g + ".")), key=lambda ig: len(ig[1]))
    return (0, "base") if best[1] in BASE else best


def test_every_module_belongs_to_a_layer():
    assert all(_group(m) for m in MODULES)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_down_the_layers(module):
    layer, group = _group(module)
    upward = []
    for target in IMPORTS[module][0]:
        t_layer, t_group = _group(target)
        if t_layer > layer or (t_layer == layer and t_group != group):
            upward.append(f"{target} ({LAYERS[t_layer][0]})")
    assert not upward, f"{module} ({LAYERS[layer][0]}) imports from above or beside: {upward}"


def test_opencascade_only_in_the_bridge():
    offenders = sorted(m for m, (_, other) in IMPORTS.items()
                       if other & {"OCP", "build123d", "cadquery"} and not m.startswith("bonecad.occ"))
    assert not offenders


#: the modules that start processes: the runner's executors (forked children; the Dask cluster)
EXECUTORS = {"bonecad.run.executor", "bonecad.run.cluster"}


def test_processes_only_in_the_executors():
    offenders = sorted(m for m, (_, other) in IMPORTS.items()
                       if other & {"multiprocessing", "subprocess", "concurrent", "dask", "distributed"}
                       and m not in EXECUTORS)
    forks = sorted(m for m, p in MODULES.items() if "os.fork" in p.read_text() and m not in EXECUTORS)
    assert not offenders and not forks


def test_gmsh_only_in_the_mesher():
    """gmsh keeps one global model and writes files: only the edge's mesher (``run/tetmesh``) calls it."""
    offenders = sorted(m for m, (_, other) in IMPORTS.items() if "gmsh" in other and m != "bonecad.run.tetmesh")
    assert not offenders


def test_no_import_cycle():
    graph = nx.DiGraph((m, t) for m, (own, _) in IMPORTS.items() for t in own if t in MODULES and t != m)
    assert list(nx.simple_cycles(graph)) == []


def test_the_kernel_knows_neither_bones_nor_opencascade():
    kernel = {m: IMPORTS[m] for m in MODULES if m.startswith("bonecad.splines")}
    allowed = {"numpy", "scipy", "__future__", "dataclasses", "functools", "typing", "math", "json", "pathlib",
               "logging", "collections", "itertools"}
    for module, (own, other) in kernel.items():
        assert other <= allowed, (module, other - allowed)
        assert all(t.startswith("bonecad.splines") or _group(t)[1] == "base" for t in own), (module, own)
