"""Imports point one way, down (issue 23).

The module import graph is read from vigproc's sources with :mod:`ast`: every
``import`` counts, at a module's top level and inside functions alike (a lazy
import keeps ``vigproc --help`` fast, but it is still an edge of the graph). Only the
body of ``if __name__ == "__main__":`` is left out: it runs as the script
``__main__``, which no module imports.

The package's folders are its layers, bottom up (:data:`LAYERS`): the foundation
(``errors``, ``atomic``, ``processes``, ``scratch``, ``_version``, the shipped ``data``), the numeric core, image and
metadata I/O, the stores, forensics, the per-frame pipeline, the front ends. A module
imports only from its own layer or below.

The graph must have no cycle; no module may import the package ``vigproc`` itself
(its ``__init__`` is the top: it re-exports, lazily). The benchmarks live outside the
package, in the repository's ``benchmarks/`` (not installed): no module imports them,
and only the ``vigproc bench`` entry reaches them, through
:func:`vigproc.frontends.commands._bench.benchmark`.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

from scripts.deferred_imports import HEAVY_STDLIB, classify
from scripts.deferred_imports import module_names as modules

PACKAGE = Path(__file__).resolve().parents[1] / "vigproc"
REPO = PACKAGE.parent
#: The benchmarks' top-level package, in the repository beside vigproc/.
BENCH = "benchmarks"

#: Functions outside the ``vigproc bench`` commands (a function whose name holds "bench")
#: that may load the benchmarks, by (module, top-level function).
BENCH_COMMANDS: set[tuple[str, str]] = set()  # the bench commands live in benchmarks/cli
#: Real commands that still load benchmark code: none (forensics calibrate's lens classes
#: and residuals are vigproc.forensics.calibration_frames).
BENCH_DEBT: set[tuple[str, str]] = set()


#: The layers, bottom up: a module imports only from its own layer or a lower one.
LAYERS = (
    ("vigproc.errors", "vigproc.atomic", "vigproc.processes", "vigproc.scratch", "vigproc._version", "vigproc.data"),
    ("vigproc.core",),
    ("vigproc.io",),
    ("vigproc.stores",),
    ("vigproc.forensics",),
    ("vigproc.pipeline",),
    # vigproc.api: the stable API's old name; vigproc.__main__: `python -m vigproc`, the command
    ("vigproc.frontends", "vigproc.api", "vigproc.__main__"),
)


def layer_of(module: str) -> int | None:
    """The index in :data:`LAYERS` of a module (None for the package ``vigproc`` itself)."""
    for i, prefixes in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    return None


@dataclass(frozen=True)
class Edge:
    """One import: ``source`` imports ``target`` at ``line``, inside top-level ``function``
    (None at module level)."""

    source: str
    target: str
    line: int
    function: str | None


def _is_main_guard(node: ast.AST) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in node.test.comparators))


def _imports(tree: ast.Module):
    """Every import node of a module with its enclosing top-level function's name,
    skipping the ``__main__`` guard's body."""
    for top in tree.body:
        if _is_main_guard(top):
            continue
        function = top.name if isinstance(top, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) else None
        for node in ast.walk(top):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                yield node, function


def import_graph(root: Path) -> list[Edge]:
    """The imports between the package's own modules (an import of a name inside a
    module is an edge to that module; of a submodule, to the submodule)."""
    mods = modules(root)
    top = root.name

    def known(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    edges = []
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node, function in _imports(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the package, one level up per extra dot
                    anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                if t == top or t.startswith(top + "."):
                    target = known(t)
                    if target is not None and target != name:
                        edges.append(Edge(name, target, node.lineno, function))
    return edges


def cycles(edges: list[Edge]) -> list[list[str]]:
    """The graph's strongly connected components of more than one module (Tarjan)."""
    adj: dict[str, set[str]] = defaultdict(set)
    for e in edges:
        adj[e.source].add(e.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(adj[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted({e.source for e in edges} | {e.target for e in edges}):
        if v not in index:
            visit(v)
    return found


def _describe(component: list[str], edges: list[Edge]) -> str:
    inside = set(component)
    return "; ".join(f"{e.source}:{e.line} -> {e.target}" for e in edges
                     if e.source in inside and e.target in inside)


@pytest.fixture(scope="module")
def graph() -> list[Edge]:
    return import_graph(PACKAGE)


def test_the_graph_sees_imports_inside_functions(graph):
    lazy = [e for e in graph if e.function is not None]
    assert len(lazy) > 100  # vigproc imports lazily for start-up time; those are edges too
    assert any(e.source == "vigproc.pipeline.processor" and e.target == "vigproc.forensics.check" for e in lazy)  # check mode's


def test_no_import_cycle(graph):
    found = cycles(graph)
    assert not found, "import cycles: " + " | ".join(_describe(c, graph) for c in found)


def test_every_module_sits_in_a_layer():
    homeless = sorted(m for m in modules(PACKAGE) if m != "vigproc" and layer_of(m) is None)
    assert not homeless, f"modules outside the layers of tests/test_layers.py: {homeless}"


def test_imports_point_down_the_layers(graph):
    up = sorted(f"{e.source}:{e.line} -> {e.target}" for e in graph
                if e.source != "vigproc" and layer_of(e.target) is not None
                and layer_of(e.target) > layer_of(e.source))
    assert not up, f"imports of a higher layer: {up}"


def test_the_layer_check_sees_an_upward_import():
    assert layer_of("vigproc.core.model") < layer_of("vigproc.stores.profiles") < layer_of("vigproc.frontends.cli")
    assert layer_of("vigproc.errors") == 0 and layer_of("vigproc") is None


def test_no_module_imports_the_package_itself(graph):
    up = [f"{e.source}:{e.line}" for e in graph if e.target == "vigproc"]
    assert not up, f"import the leaf module instead (vigproc._version for __version__): {up}"


def benchmark_uses(root: Path) -> tuple[list[str], set[tuple[str, str | None]]]:
    """Import statements of the benchmarks anywhere in the package (``module:line``), and
    the (module, top-level function) pairs that load them by name through ``benchmark(...)``."""
    imports, loads = [], set()
    for name, path in modules(root).items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for top in tree.body:
            function = top.name if isinstance(top, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) else None
            for node in ast.walk(top):
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and not node.level:
                    targets = [node.module or ""]
                else:
                    targets = []
                if any(t == BENCH or t.startswith(BENCH + ".") for t in targets):
                    imports.append(f"{name}:{node.lineno}")
                if isinstance(node, ast.Call) and (getattr(node.func, "id", None) == "benchmark"
                                                   or getattr(node.func, "attr", None) == "benchmark"):
                    loads.add((name, function))
    return imports, loads


def test_the_package_never_imports_the_benchmarks():
    imports, _ = benchmark_uses(PACKAGE)
    assert not imports, f"the installed package cannot import the benchmarks (not installed): {imports}"
    assert not (PACKAGE / "bench").exists(), "the benchmarks live in the repository's benchmarks/, not in vigproc/"


def test_only_bench_commands_load_the_benchmarks():
    _, loads = benchmark_uses(PACKAGE)
    unexpected = sorted(f"{m}.{f or '<module>'}" for m, f in loads
                        if not (f and "bench" in f) and (m, f) not in BENCH_COMMANDS | BENCH_DEBT)
    assert not unexpected, f"real commands loading the benchmarks: {unexpected}"
    assert not BENCH_DEBT, f"commands still loading benchmark code: {sorted(BENCH_DEBT)}"
    stale = BENCH_COMMANDS - loads
    assert not stale, f"no longer load the benchmarks, remove from BENCH_COMMANDS: {sorted(stale)}"
    assert ("vigproc.frontends.commands.forensics", "cmd_calibrate") not in loads  # product code, no benchmark


def test_the_benchmark_check_sees_a_load_and_an_import(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def cmd_x():\n    return benchmark('clean')\n")
    (pkg / "b.py").write_text("def f():\n    from benchmarks.clean import run\n    import benchmarks\n")
    imports, loads = benchmark_uses(pkg)
    assert imports == ["pkg.b:2", "pkg.b:3"] and loads == {("pkg.a", "cmd_x")}


def test_the_wheel_holds_no_benchmarks():
    """pyproject's package list (setuptools' find over the repository) is vigproc's own
    packages: neither ``benchmarks`` nor anything under it."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    setuptools = pytest.importorskip("setuptools")
    config = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    find = config["tool"]["setuptools"]["packages"]["find"]
    packages = setuptools.find_packages(str(REPO), include=find.get("include", ["*"]), exclude=find.get("exclude", ()))
    assert "vigproc" in packages and "vigproc.core" in packages
    shipped = [p for p in packages if p == BENCH or p.startswith(BENCH + ".") or not p.startswith("vigproc")]
    assert not shipped, f"packages installed beside vigproc: {shipped}"
    assert (REPO / BENCH / "__init__.py").is_file()  # the benchmarks are there, in the checkout


def test_the_checker_finds_a_cycle_through_a_function_level_import(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.b import g\n")
    (pkg / "b.py").write_text("def g():\n    from . import a\n    return a\n")
    (pkg / "c.py").write_text("import pkg.a\nif __name__ == '__main__':\n    import pkg.d\n")
    (pkg / "d.py").write_text("import pkg.c\n")
    edges = import_graph(pkg)
    assert cycles(edges) == [["pkg.a", "pkg.b"]]  # c -> d is only the script's: no cycle c, d
    assert Edge("pkg.b", "pkg.a", 2, "g") in edges


def test_the_deferred_import_count_sees_each_reason(tmp_path):
    """scripts/deferred_imports.py: a function-level import is ``start-up`` when it loads
    what the module's top level does not (a third-party package, a heavy part of the
    standard library), ``optional`` inside ``try: ... except ImportError``, else
    ``needless``."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "light.py").write_text("X = 1\n")
    (pkg / "a.py").write_text(
        "import os\n"
        "def f():\n    import os\n    from pkg.light import X\n    return os, X\n"
        "def g():\n    import numpy\n    import asyncio\n    return numpy, asyncio\n"
        "def h():\n    try:\n        import lensfunpy\n    except ImportError:\n        return None\n")
    got = {(line, reason) for module, line, _, reason in classify(pkg) if module == "pkg.a"}
    assert got == {(3, "needless"), (4, "needless"), (7, "start-up"), (8, "start-up"), (12, "optional")}
    assert "asyncio" in HEAVY_STDLIB


#: Modules allowed over :data:`MAX_LINES` say why at the top of their docstring, in these words.
LARGE_REASON = "over the house's 1000 lines"
MAX_LINES = 1000


def test_modules_over_1000_lines_say_why():
    """One concept per module: a module over 1000 lines states, in its docstring, why it is
    one module (issue 40)."""
    silent = []
    for name, path in modules(PACKAGE).items():
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_LINES and LARGE_REASON not in (ast.get_docstring(ast.parse(text)) or ""):
            silent.append(f"{name} ({text.count(chr(10))} lines)")
    assert not silent, f"split these, or say why each is one module ('{LARGE_REASON}'): {silent}"
