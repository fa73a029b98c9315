"""The package's import graph: no import cycle anywhere in ``slamkit/``, and no stage module importing another;
and no module of ``slamkit/`` grows past :data:`MAX_MODULE_LINES` lines.

Every ``import`` / ``from ... import`` of a slamkit module counts, at module level or inside a function
(an import hidden in a function still runs, and still closes a cycle); only imports under
``if TYPE_CHECKING:`` are left out (annotations, never executed). Read with ``ast``: nothing is imported.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "slamkit"
STAGES = "slamkit.stages"

KNOWN_CYCLES: list[set[str]] = []
"""Cycles another branch removes (each entry one strongly connected component); the test fails when one of
them is gone, so the list cannot outlive the fix."""


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST):
    """Import nodes anywhere in the tree except in ``if TYPE_CHECKING:`` blocks."""
    stack = [tree]
    while stack:
        node = stack.pop()
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                stack.extend(child.orelse)
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                yield child
            stack.append(child)


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph() -> dict[str, set[str]]:
    """slamkit module -> the slamkit modules it imports (a submodule named in ``from pkg import sub`` counts
    as that submodule)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in _import_nodes(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                target = _resolve(module, is_package, node)
                subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules]
                targets = subs or [target]
            for t in targets:
                while t and t not in modules:  # "slamkit.x.y" where y is a name: the module is slamkit.x
                    t = t.rpartition(".")[0]
                if t.startswith("slamkit") and t != module:
                    graph[module].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as one cycle through it."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(_cycle_in(graph, set(comp)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _cycle_in(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """One closed path a -> ... -> a inside a strongly connected component (for the failure message)."""
    start = min(comp)
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v] & comp):
            if w == start:
                return paths[v] + [start]
            if w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    return sorted(comp)  # pragma: no cover - a component always has a cycle through each member


def test_the_checker_finds_a_cycle_and_resolves_relative_imports():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c", "a"]]
    g = import_graph()
    assert "slamkit.map" in g["slamkit.stages.mapper"] and "slamkit.camera" in g["slamkit.map"]


def test_no_import_cycles():
    found = cycles(import_graph())
    unexpected = [c for c in found if set(c) not in KNOWN_CYCLES]
    assert not unexpected, "import cycles in slamkit/: " + "; ".join(" -> ".join(c) for c in unexpected)
    gone = [k for k in KNOWN_CYCLES if k not in [set(c) for c in found]]
    assert not gone, f"these cycles are gone: remove them from KNOWN_CYCLES: {gone}"


def _stage(module: str) -> str:
    """The stage a module of ``slamkit.stages`` belongs to: itself, or the package it is part of (a stage too large
    for one module is a package, e.g. ``slamkit.stages.self_calibration``, whose modules import each other)."""
    return ".".join(module.split(".")[:3])


def test_stages_do_not_import_each_other():
    graph = import_graph()
    bad = {m: sorted(t for t in targets if t.startswith(STAGES + ".") and _stage(t) != _stage(m))
           for m, targets in graph.items() if m.startswith(STAGES + ".")}
    bad = {m: t for m, t in bad.items() if t}
    assert not bad, f"stage modules import other stage modules (move shared helpers to kernels/geometry.py or map.py): {bad}"


MAX_MODULE_LINES = 600
"""A module that grows past this is doing two things (issue 39: the pipeline had grown to 690 lines, mostly
self-calibration's glue, which went to ``slamkit/run_camera.py``)."""


def test_every_module_stays_under_600_lines():
    sizes = {m: len(p.read_text(encoding="utf-8").splitlines()) for m, p in _modules().items()}
    assert sizes["slamkit.pipeline"] > 100  # the count reads the real files
    big = {m: n for m, n in sizes.items() if n >= MAX_MODULE_LINES}
    assert not big, f"modules of {MAX_MODULE_LINES} lines or more (split them by what they do): {big}"


KERNELS = "slamkit.kernels"
KERNEL_MODULES = ("absolute_pose", "geometry", "local_ba", "pose_graph", "pose_optimization", "sim3")
"""The kernels issue 48 moved into the layer; the test fails when one of them leaves it."""
KERNEL_DEPENDENCIES = {"__future__", "dataclasses", "math", "typing", "numpy", "numba", "scipy"}
"""What a kernel may import besides ``slamkit.kernels`` (and ``slamkit.errors``): numerics and the standard
library's plumbing; never pycolmap, pyceres, OpenCV or the map."""


def _external_imports(path: Path) -> set[str]:
    """Top-level names of every module a file imports (``import a.b`` -> ``a``; relative imports left out)."""
    out = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_the_kernel_checker_sees_imports_inside_functions(tmp_path):
    source = tmp_path / "kernel.py"
    source.write_text("import numpy as np\n\n\ndef f():\n    import pycolmap\n    from cv2 import imread\n"
                      "    from . import sim3\n    return pycolmap, imread, sim3\n")
    assert _external_imports(source) == {"numpy", "pycolmap", "cv2"}


def test_kernels_import_neither_pycolmap_nor_the_stages():
    """The numerical kernels (issue 48) work on plain arrays: a worker thread runs them beside tracking, and the
    stages build their input from the map; they import no pycolmap and no slamkit module outside the kernels
    but the errors, at module level or inside a function."""
    modules = _modules()
    kernels = {m: p for m, p in modules.items() if m == KERNELS or m.startswith(KERNELS + ".")}
    missing = [k for k in KERNEL_MODULES if f"{KERNELS}.{k}" not in kernels]
    assert not missing, f"kernel modules missing from slamkit/kernels: {missing}"
    graph = import_graph()
    allowed = {"slamkit.errors"}
    bad = {m: sorted(t for t in graph[m] if not (t == KERNELS or t.startswith(KERNELS + ".")) and t not in allowed)
           for m in kernels}
    bad = {m: t for m, t in bad.items() if t}
    assert not bad, f"kernel modules import slamkit modules outside slamkit/kernels: {bad}"
    foreign = {m: sorted(_external_imports(p) - KERNEL_DEPENDENCIES - {"slamkit"}) for m, p in kernels.items()}
    foreign = {m: n for m, n in foreign.items() if n}
    assert not foreign, (f"kernel modules import more than {sorted(KERNEL_DEPENDENCIES)} (pycolmap, pyceres, "
                         f"OpenCV and the map stay outside slamkit/kernels): {foreign}")
