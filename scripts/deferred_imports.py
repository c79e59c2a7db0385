"""Count vigproc's function-level (deferred) imports and say why each is deferred.

An import inside a function is paid when the function first runs instead of when its
module is imported. That is worth it for two reasons only:

* ``start-up``: the import loads a third-party package (numpy, OpenImageIO, Dask, ...)
  or a heavy part of the standard library (:data:`HEAVY_STDLIB`) or a large part of
  vigproc itself (:data:`MANY` modules or more),
  directly or through vigproc modules' top-level imports, that the importing module's
  own top-level imports do not load already: deferring it keeps ``vigproc --help``, a
  hook call or a light module fast. In the modules ``vigproc --help`` and ``import
  vigproc`` load (:data:`LIGHT_ROOTS` and their top-level imports) any module not loaded
  yet counts: their start-up is a target (``tests/test_startup.py``);
* ``optional``: it sits in a ``try`` that catches ``ImportError`` (or reads
  ``find_spec``), so a missing package degrades one feature instead of the module.

Every other deferred import (``needless``: the package or module is loaded by the
importer's top level already, or it is standard library that costs nothing worth
deferring) could be written at the module's top. Run from the repository root::

    python scripts/deferred_imports.py            # the counts by reason
    python scripts/deferred_imports.py --list     # and every needless one, file:line

The exit status is 1 when a needless one is found (``--list`` names them).
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vigproc"
#: Standard-library modules that take tens of milliseconds or more to import (``python -X
#: importtime``: asyncio, concurrent.futures.process, importlib.metadata, tomllib, sqlite3,
#: json each 20-200 ms on this machine under load), deferred like a third-party package.
HEAVY_STDLIB = ("asyncio", "concurrent", "multiprocessing", "importlib.metadata", "tomllib", "sqlite3", "json",
                "email", "http", "urllib", "xml", "ssl", "socket", "argparse", "subprocess")
#: A deferred import that loads this many of vigproc's modules not loaded yet defers a
#: large part of the package (``vigproc.pipeline.processor`` alone: about 170 ms under load).
MANY = 8
#: What ``vigproc --help`` and ``import vigproc`` load: kept light on purpose.
LIGHT_ROOTS = ("vigproc.frontends.cli", "vigproc", "vigproc.io")


def module_names(root: Path) -> dict[str, Path]:
    """Dotted module name -> source file for every ``.py`` under the package ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _targets(node: ast.AST, module: str, is_package: bool, mods: dict[str, Path]) -> list[str]:
    """The dotted names an import statement loads (relative imports resolved)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        package = module if is_package else module.rpartition(".")[0]
        parts = package.split(".")
        anchor = parts[: len(parts) - (node.level - 1)]
        base = ".".join(anchor + ([base] if base else []))
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]


def _loaded(name: str, mods: dict[str, Path]) -> list[str]:
    """The vigproc modules importing ``name`` runs (the package ``__init__`` files on the way too)."""
    parts = name.split(".")
    return [m for m in (".".join(parts[:i]) for i in range(1, len(parts) + 1)) if m in mods]


def _guarded(parents: list[ast.AST]) -> bool:
    """Inside ``try: ... except ImportError`` (or ModuleNotFoundError)?"""
    for p in parents:
        if isinstance(p, ast.Try):
            for h in p.handlers:
                names = [h.type] if not isinstance(h.type, ast.Tuple) else list(h.type.elts)
                if any(getattr(n, "id", None) in ("ImportError", "ModuleNotFoundError") for n in names):
                    return True
    return False


def scan(root: Path = PACKAGE):
    """Top-level imports of every module, and every deferred import with its enclosing nodes.

    Returns
    -------
    mods : dict
        Module name -> path.
    top : dict
        Module name -> set of dotted names its top level imports (``if TYPE_CHECKING`` left out).
    deferred : list of (module, line, targets, guarded)
        One row per import statement inside a function.
    """
    mods = module_names(root)
    top: dict[str, set[str]] = {}
    deferred = []
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        is_package = path.name == "__init__.py"
        top[name] = set()

        def walk(node, parents, in_function):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                    continue
                if isinstance(child, ast.If) and "__main__" in ast.unparse(child.test):
                    continue  # the script's own entry: no module imports it
                if isinstance(child, (ast.Import, ast.ImportFrom)):
                    targets = _targets(child, name, is_package, mods)
                    if in_function:
                        deferred.append((name, child.lineno, sorted(set(targets)), _guarded(parents)))
                    else:
                        top[name].update(targets)
                inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                walk(child, parents + [child], inner)

        walk(tree, [], False)
    return mods, top, deferred


def closure(start: set[str], mods: dict[str, Path], top: dict[str, set[str]]) -> set[str]:
    """Every dotted name loaded by importing ``start`` (vigproc modules followed through
    their top-level imports; others kept as their top-level package name)."""
    package = min(mods, key=len)
    seen: set[str] = set()
    todo = list(start)
    while todo:
        t = todo.pop()
        inner = _loaded(t, mods) if t.split(".")[0] == package else []
        if not inner:
            seen.add(t.split(".")[0])
            if t.split(".")[0] != package:
                seen.add(t)  # dotted too: importlib.metadata is not importlib
            continue
        for m in inner:
            if m not in seen:
                seen.add(m)
                todo.extend(top[m])
    return seen


def classify(root: Path = PACKAGE):
    """Each deferred import of the package with its reason: ``start-up``, ``optional`` or ``needless``.

    Returns
    -------
    list of (module, line, targets, reason)
    """
    mods, top, deferred = scan(root)
    package = min(mods, key=len)
    stdlib = set(sys.stdlib_module_names)
    out = []
    cache: dict[str, set[str]] = {}
    light = closure(set(LIGHT_ROOTS), mods, top)
    for module, line, targets, guarded in deferred:
        if module not in cache:
            cache[module] = closure(top[module] | {module}, mods, top)
        adds = closure(set(targets), mods, top) - cache[module]
        third_party = {a for a in adds if "." not in a and a != package and a not in stdlib and a not in mods}
        third_party |= {a for a in adds if any(a == h or a.startswith(h + ".") for h in HEAVY_STDLIB)}
        if guarded:
            reason = "optional"
        elif third_party or (module in light and adds) or len({a for a in adds if a.startswith(package + ".")}) >= MANY:
            reason = "start-up"
        else:
            reason = "needless"
        out.append((module, line, ", ".join(targets), reason))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="name every needless deferred import")
    args = ap.parse_args(argv)
    rows = classify()
    counts = Counter(r for *_, r in rows)
    print(f"deferred imports in vigproc/: {len(rows)} "
          + " ".join(f"{k}={counts.get(k, 0)}" for k in ("start-up", "optional", "needless")))
    if args.list:
        for module, line, target, reason in rows:
            if reason == "needless":
                print(f"  {module}:{line} {target}")
    return 1 if counts.get("needless") else 0


if __name__ == "__main__":
    sys.exit(main())
