"""The examples in vigproc's docstrings run, and say what they print (issue 23).

Every module of the package whose source holds an example (``>>>``) is run through
:mod:`doctest`, so a new example is collected without listing it here; the public
functions and classes must have one.  The examples use small synthetic arrays and
fixed seeds: they are deterministic and take about a second together.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import io
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "vigproc"
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _modules_with_examples() -> list[str]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>>" not in path.read_text(encoding="utf-8"):
            continue
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


#: What a user reads first: each of these has an example of its own.
PUBLIC = [
    "vigproc",
    "vigproc.core.estimate.estimate",
    "vigproc.core.correct.correct",
    "vigproc.core.model.VignettingModel",
    "vigproc.core.model.VignettingModel.field",
    "vigproc.core.model.VignettingModel.rescale",
    "vigproc.core.model.VignettingModel.to_json",
    "vigproc.core.model.VignettingModel.from_json",
    "vigproc.frontends.api",
    "vigproc.frontends.api.Pipeline",
]


@pytest.mark.parametrize("name", _modules_with_examples())
def test_examples_run(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # an example that writes a file writes it here
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    report = io.StringIO()
    tests = [t for t in finder.find(module, name) if t.examples]
    for t in tests:
        runner.run(t, out=report.write)
    results = runner.summarize(verbose=False)
    assert results.failed == 0, report.getvalue()


@pytest.mark.parametrize("name", PUBLIC)
def test_public_names_have_examples(name):
    parts = name.split(".")
    for i in range(len(parts), 0, -1):  # the longest importable prefix, then attributes
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        break
    tests = doctest.DocTestFinder(recurse=False).find(obj, name)
    assert tests and tests[0].examples, f"{name} has no example in its docstring"
    home = obj.__name__ if inspect.ismodule(obj) else obj.__module__
    assert home in _modules_with_examples()  # and test_examples_run runs it
