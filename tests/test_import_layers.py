"""The Python package imports in one direction: no import cycles, and no import goes up a layer.

The import graph is read from the source with :mod:`ast` (nothing is imported): every
``import`` and ``from ... import`` statement of a module counts, at module level or inside a
function, class or ``try`` -- a lazy import still makes the importer depend on the imported
module. Relative imports are resolved to module names. ``from P import x`` imports the
submodule ``P.x`` when there is one, else it imports the package ``P`` itself (whose
``__init__`` defines ``x``); importing a package means importing its ``__init__``. The layers
and the rules are in ``docs/architecture.md`` ("Python layers").

Two rules keep the graph to what really runs:

* Imports under ``if TYPE_CHECKING:`` are skipped: they never execute, so they cannot form a
  cycle at run time, and they serve annotations only (strings under ``from __future__ import
  annotations``). Use them for nothing else.
* Importing ``acm_rs.a.b`` first runs the ``__init__`` of ``acm_rs`` and of ``acm_rs.a``. Such
  an implicit package import is an edge unless the package contains the importer: a module is
  always imported after (or while) its own packages, so those edges would make every package a
  cycle with its submodules. Naming something a package's ``__init__`` defines
  (``from .. import __version__``) is always an edge.
"""

from __future__ import annotations

import ast
import importlib.util
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = "acm_rs"

#: Layer of each module or package (a package's entry covers its submodules unless one has its
#: own entry; the longest matching name wins). An import may go to the same or a lower layer,
#: never to a higher one; within a layer the imports must still be acyclic.
LAYERS: dict[str, int] = {
    # 6: the command line: parses arguments and dispatches. Nothing below imports it.
    "acm_rs.cli": 6,
    "acm_rs.tracking.cli": 6,
    "acm_rs.calibration.cli": 6,
    "acm_rs.gapfill.cli": 6,
    # 5: the public facade (``acm_rs/__init__.py``): re-exports the layers below so users can
    # write ``acm_rs.track``; it imports nearly everything, so no module below may import it.
    "acm_rs": 5,
    # 4: workflows over files and folders: several algorithms and outputs in a row.
    "acm_rs.pipeline": 4,
    "acm_rs.batch": 4,
    "acm_rs.project": 4,
    "acm_rs.run_acm": 4,
    "acm_rs.demo": 4,
    # 3: outputs of tracking results (they read a PoseResult): files and figures.
    "acm_rs.export": 3,
    "acm_rs.plots": 3,
    # 2: the algorithms and the types they return (PoseResult, CalibrationResult, FillResult).
    "acm_rs.learning": 2,
    "acm_rs.elastic": 2,
    "acm_rs.tracking": 2,
    "acm_rs.calibration": 2,
    "acm_rs.gapfill": 2,
    "acm_rs.datasets": 2,
    "acm_rs.lab_skeleton": 2,
    "acm_rs.evaluate": 2,
    # 1: data types, their files and the input readers; figure helpers.
    "acm_rs.skeleton": 1,
    "acm_rs.state": 1,
    "acm_rs.camera": 1,
    "acm_rs.rotation": 1,
    "acm_rs.models": 1,
    "acm_rs.dlc": 1,
    "acm_rs.sleap": 1,
    "acm_rs.sleap_session": 1,
    "acm_rs.labels": 1,
    "acm_rs.acm_formats": 1,
    "acm_rs.acm_model": 1,
    "acm_rs.plotting": 1,
    # 0: the compiled core and small helpers that import nothing of acm_rs.
    "acm_rs._native": 0,
    "acm_rs._arrays": 0,
    "acm_rs._io": 0,
    "acm_rs._toml": 0,
    "acm_rs._version": 0,
    "acm_rs._provenance": 0,
    # the independent ground truth of the synthetic data (issue 25): NumPy only
    "acm_rs.truth": 0,
}


def _package_dir() -> Path:
    spec = importlib.util.find_spec(PACKAGE)
    assert spec is not None and spec.submodule_search_locations
    return Path(next(iter(spec.submodule_search_locations)))


def _modules(root: Path) -> dict[str, tuple[Path | None, bool]]:
    """``{module name: (source file or None, is a package)}``."""
    mods: dict[str, tuple[Path | None, bool]] = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        mods[".".join((PACKAGE,) + parts)] = (path, is_pkg)
    # the compiled extension (a .so, described by _native.pyi): imports nothing from Python
    mods.setdefault(f"{PACKAGE}._native", (None, False))
    return mods


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(node: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement below ``node`` except those under ``if TYPE_CHECKING:``."""
    if isinstance(node, ast.Import | ast.ImportFrom):
        yield node
        return
    if isinstance(node, ast.If) and _is_type_checking(node.test):
        for child in node.orelse:
            yield from _import_nodes(child)
        return
    for child in ast.iter_child_nodes(node):
        yield from _import_nodes(child)


def _own_packages(name: str, is_pkg: bool) -> set[str]:
    """The packages that contain a module (a package contains itself)."""
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts) + (1 if is_pkg else 0))}


def _with_packages(target: str, own: set[str], mods: dict) -> Iterator[str]:
    """``target`` and the packages above it that importing it runs (not the importer's own)."""
    yield _existing(target, mods)
    parts = target.split(".")
    for i in range(1, len(parts)):
        pkg = ".".join(parts[:i])
        if pkg not in own:
            yield pkg


def _targets(
    node: ast.Import | ast.ImportFrom, name: str, is_pkg: bool, mods: dict
) -> Iterator[tuple[str, int]]:
    """Modules of the package imported by one statement, with its line number."""
    own = _own_packages(name, is_pkg)
    if isinstance(node, ast.Import):
        for alias in node.names:
            if alias.name == PACKAGE or alias.name.startswith(PACKAGE + "."):
                for t in _with_packages(alias.name, own, mods):
                    yield t, node.lineno
        return
    if node.level:
        base = name.split(".") if is_pkg else name.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        assert base, f"{name}: relative import beyond the top-level package"
        base_name = ".".join(base + ([node.module] if node.module else []))
    else:
        base_name = node.module or ""
        if not (base_name == PACKAGE or base_name.startswith(PACKAGE + ".")):
            return
    for alias in node.names:
        sub = f"{base_name}.{alias.name}"
        if sub in mods:  # a submodule; its package runs first
            for t in _with_packages(sub, own, mods):
                yield t, node.lineno
        else:  # a name defined by the module (or package __init__) base_name
            yield _existing(base_name, mods), node.lineno
            for t in _with_packages(base_name, own, mods):
                yield t, node.lineno


def _existing(name: str, mods: dict) -> str:
    assert name in mods, f"import of {name}, which is not a module of {PACKAGE}"
    return name


def import_graph(root: Path | None = None) -> dict[str, dict[str, int]]:
    """``{importer: {imported: first line}}`` over the modules of the package (in ``root``)."""
    mods = _modules(_package_dir() if root is None else root)
    graph: dict[str, dict[str, int]] = {m: {} for m in mods}
    for name, (path, is_pkg) in mods.items():
        if path is None:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in _import_nodes(tree):
            for target, line in _targets(node, name, is_pkg, mods):
                if target != name:
                    graph[name].setdefault(target, line)
    return graph


def components(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    comps: list[list[str]] = []

    def visit(v: str) -> None:  # the package is small: recursion depth < 100
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(comps)


def shortest_cycle(start: str, members: set[str], graph: dict[str, dict[str, int]]) -> list[str]:
    """A shortest cycle ``[start, ..., start]`` inside a strongly connected component."""
    prev: dict[str, str] = {}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v]):
            if w not in members:
                continue
            if w == start:
                path = [v]
                while path[-1] != start:
                    path.append(prev[path[-1]])
                return path[::-1] + [start]
            if w not in prev:
                prev[w] = v
                queue.append(w)
    raise AssertionError(f"{start} is on no cycle")  # pragma: no cover


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Import cycles: a shortest one through every module that is on a cycle (duplicates
    removed), so each module of every strongly connected component shows up."""
    found: dict[tuple[str, ...], list[str]] = {}
    for comp in components(graph):
        for start in comp:
            cyc = shortest_cycle(start, set(comp), graph)
            ring = cyc[:-1]
            i = ring.index(min(ring))
            found.setdefault(tuple(ring[i:] + ring[:i]), cyc)
    return list(found.values())


def layer_of(module: str) -> int:
    """Layer of a module: its own entry or that of its closest package below ``acm_rs``."""
    name = module
    while name not in LAYERS or (name == PACKAGE and module != PACKAGE):
        assert "." in name, f"{module} has no layer: add it to LAYERS in {__file__}"
        name = name.rsplit(".", 1)[0]
    return LAYERS[name]


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    return import_graph()


def test_the_graph_sees_the_imports(graph):
    # a few known edges of each kind: top level, in a function, `from . import submodule`,
    # relative beyond the parent package
    assert "acm_rs.skeleton" in graph["acm_rs.learning"]
    assert "acm_rs.demo" in graph["acm_rs.cli"]  # inside _cmd_demo
    assert "acm_rs._native" in graph["acm_rs.rotation"]  # from . import _native
    assert "acm_rs.export" in graph["acm_rs.pipeline"]  # from . import export (a package)
    assert "acm_rs.camera" in graph["acm_rs.calibration.solve"]  # from ..camera import
    assert "acm_rs.tracking.result" in graph["acm_rs.tracking"]  # package __init__
    # `from .tracking import track` (a function and a submodule): the package and the submodule
    assert {"acm_rs.tracking", "acm_rs.tracking.track"} <= set(graph["acm_rs.run_acm"])
    # importing a sibling submodule is no edge to one's own package ...
    assert "acm_rs.calibration" not in graph["acm_rs.calibration.result"]  # from . import world
    # ... but a submodule of another package also runs (depends on) that package's __init__
    assert {"acm_rs.tracking", "acm_rs.tracking.result_npz"} <= set(graph["acm_rs.export.npz"])
    # under `if TYPE_CHECKING:` only
    assert "acm_rs.camera" not in graph["acm_rs.plotting"]


def test_the_cycle_check_finds_hidden_cycles(tmp_path):
    # a throw-away package: a cycle through a function-level import (a <-> b) and one through
    # another package's __init__ (b -> pkg.c runs pkg, which imports b); a TYPE_CHECKING import
    # is no edge; `from . import NAME` (not a submodule) is an edge to the package
    files = {
        "__init__.py": "from .a import f\n",
        "_native.py": "",
        "a.py": "def f():\n    from . import b\n",
        "b.py": "from .a import f\nfrom .pkg.c import g\n",
        "pkg/__init__.py": "from .. import b\n",
        "pkg/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..d import h\n",
        "d.py": "import acm_rs.pkg.c\n",
        "e.py": "from . import VERSION\n",
    }
    for name, text in files.items():
        (tmp_path / PACKAGE / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / PACKAGE / name).write_text(text)
    g = import_graph(tmp_path / PACKAGE)
    assert g["acm_rs.a"] == {"acm_rs.b": 2}
    assert g["acm_rs.b"] == {"acm_rs.a": 1, "acm_rs.pkg": 2, "acm_rs.pkg.c": 2}
    assert g["acm_rs.pkg.c"] == {}
    assert g["acm_rs.d"] == {"acm_rs.pkg": 1, "acm_rs.pkg.c": 1}
    assert g["acm_rs.e"] == {"acm_rs": 1}
    assert components(g) == [["acm_rs.a", "acm_rs.b", "acm_rs.pkg"]]
    found = cycles(g)
    assert all(
        c[0] == c[-1] and all(b in g[a] for a, b in zip(c, c[1:], strict=False)) for c in found
    )
    assert sorted(sorted(set(c)) for c in found) == [
        ["acm_rs.a", "acm_rs.b"],
        ["acm_rs.b", "acm_rs.pkg"],
    ]


def test_no_import_cycles(graph):
    comps = components(graph)

    def show(cycle: list[str]) -> str:
        return " -> ".join(
            [cycle[0]]
            + [f"{b} (line {graph[a][b]})" for a, b in zip(cycle, cycle[1:], strict=False)]
        )

    assert not comps, (
        f"{len(comps)} group(s) of modules import each other: "
        + "; ".join(f"[{', '.join(c)}]" for c in comps)
        + "\ncycles (a shortest one through each module; line of the import in the importer):\n  "
        + "\n  ".join(show(c) for c in cycles(graph))
    )


def test_every_module_has_a_layer(graph):
    for module in graph:
        layer_of(module)
    for name in LAYERS:
        assert name in graph, f"LAYERS names {name}, which is not a module of {PACKAGE}"


def test_imports_go_down(graph):
    upward = [
        f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)}) on line {line}"
        for a, targets in sorted(graph.items())
        for b, line in sorted(targets.items())
        if layer_of(b) > layer_of(a)
    ]
    assert not upward, f"{len(upward)} upward import(s):\n  " + "\n  ".join(upward)


def test_the_truth_shares_no_code_with_acm_rs(graph):
    """``acm_rs.truth`` makes the ground truth of every synthetic accuracy figure; it must
    import nothing of acm_rs (not even the helpers of layer 0), or a defect could hide in its
    own truth."""
    assert graph["acm_rs.truth"] == {}
    source = (_package_dir() / "truth.py").read_text()
    imported = {
        alias.name.split(".")[0]
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Import | ast.ImportFrom)
        for alias in (
            node.names if isinstance(node, ast.Import) else [ast.alias(node.module or ".")]
        )
    }
    assert imported <= {"__future__", "numpy"}, imported
