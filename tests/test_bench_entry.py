"""``vigproc bench`` finds the benchmarks in a source checkout (they are not installed),
or through ``--benchmarks-dir`` / ``$VIGPROC_BENCHMARKS``, and says so when it cannot."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vigproc.errors import BenchmarksNotFoundError
from vigproc.frontends import cli
from vigproc.frontends.commands import _bench

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_choice(monkeypatch):
    """No --benchmarks-dir left over from another test, no $VIGPROC_BENCHMARKS."""
    monkeypatch.setattr(_bench, "_chosen", [])
    monkeypatch.delenv(_bench.BENCHMARKS_ENV, raising=False)


def test_a_checkout_finds_its_own_benchmarks(no_choice):
    assert _bench.benchmarks_dir() == REPO / "benchmarks"
    clean = _bench.benchmark("clean")
    assert Path(clean.__file__).resolve() == REPO / "benchmarks" / "clean.py"


def test_an_installed_copy_says_where_the_benchmarks_are(no_choice, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(_bench, "CHECKOUT_BENCHMARKS", tmp_path / "site-packages" / "benchmarks")
    with pytest.raises(BenchmarksNotFoundError, match="not installed"):
        _bench.benchmark("clean")
    assert cli.main(["bench", "io"]) == BenchmarksNotFoundError.exit_code != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "source checkout" in err[0] and "--benchmarks-dir" in err[0], err


def test_benchmarks_dir_takes_the_folder_or_the_checkout(no_choice, monkeypatch, tmp_path):
    monkeypatch.setattr(_bench, "CHECKOUT_BENCHMARKS", tmp_path / "nowhere" / "benchmarks")
    for given in (REPO, REPO / "benchmarks"):
        monkeypatch.setattr(_bench, "_chosen", [])
        cli.build_parser().parse_args(["bench", "--benchmarks-dir", str(given), "io"])
        assert _bench.benchmarks_dir() == REPO / "benchmarks"
    monkeypatch.setattr(_bench, "_chosen", [])
    monkeypatch.setenv(_bench.BENCHMARKS_ENV, str(REPO))
    assert _bench.benchmarks_dir() == REPO / "benchmarks"


def test_a_wrong_benchmarks_dir_is_a_typed_error(no_choice, monkeypatch, tmp_path, capsys):
    (tmp_path / "benchmarks").mkdir()  # a folder by that name without the package
    assert cli.main(["bench", "--benchmarks-dir", str(tmp_path), "io"]) == BenchmarksNotFoundError.exit_code
    assert "neither a vigproc benchmarks/ folder" in capsys.readouterr().err
    monkeypatch.setattr(_bench, "_chosen", [])
    monkeypatch.setenv(_bench.BENCHMARKS_ENV, str(tmp_path / "missing"))
    with pytest.raises(BenchmarksNotFoundError):
        _bench.benchmarks_dir()


def test_a_copy_of_the_package_alone_runs_everything_but_bench(tmp_path):
    """The installed layout for real: vigproc/ without benchmarks/ beside it, in a new
    process. ``vigproc bench`` (a benchmark's help too: its options live in benchmarks/)
    fails in one line (exit 1); ``vigproc --help`` and the product's commands that used
    benchmark code (forensics calibrate) still load."""
    shutil.copytree(REPO / "vigproc", tmp_path / "vigproc", ignore=shutil.ignore_patterns("__pycache__"))
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(tmp_path), "HOME": str(tmp_path)}
    run = lambda *a: subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", *a], cwd=tmp_path,  # noqa: E731
                                    env=env, capture_output=True, text=True, timeout=300)
    r = run("bench", "synthetic", "--images", str(tmp_path))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert r.stderr.strip().startswith("vigproc: the benchmarks are not installed with vigproc"), r.stderr
    for argv in (("bench", "clean", "--help"), ("bench", "--help")):
        r = run(*argv)
        assert r.returncode == 1 and r.stderr.strip().startswith("vigproc: the benchmarks are not installed"), r.stderr
    r = run("--help")
    assert r.returncode == 0 and "bench" in r.stdout and "Traceback" not in r.stderr
    code = ("import sys; import vigproc.forensics.calibration_frames as m, vigproc.frontends.commands.forensics; "
            "assert 'benchmarks' not in sys.modules; print(m.__file__)")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.startswith(str(tmp_path)), r.stderr


def test_python_m_benchmarks_is_vigproc_bench():
    """From the checkout's root, ``python -m benchmarks NAME`` runs ``vigproc bench NAME``
    on that checkout's benchmarks."""
    r = subprocess.run([sys.executable, "-m", "benchmarks", "--help"], cwd=REPO, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and "usage: vigproc bench" in r.stdout and "real-frames" in r.stdout, r.stderr
    r = subprocess.run([sys.executable, "-m", "benchmarks", "io", "--exif"], cwd=REPO, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 2 and "--exif: expected one argument" in r.stderr  # vigproc bench io's own parser


def test_a_bench_table_prints_as_its_columns_say(capsys):
    """The one helper the bench commands print their tables with: a title takes its
    column's alignment and width, a number the whole spec, a text value ('-') the width."""
    from benchmarks.cli._common import Table

    t = Table((("method", "<8"), ("n", ">4"), ("median EV", ">10.3f")))
    assert t.header() == f"{'method':<8}{'n':>4}{'median EV':>10}"
    assert t.row("default", 12, 0.12345) == f"{'default':<8}{12:>4}{0.12345:>10.3f}"
    assert t.row("rgs", 3, "-") == f"{'rgs':<8}{3:>4}{'-':>10}"
    with pytest.raises(ValueError):
        t.row("default", 12)
    t.print_rows([("a", 1, 1.0), ("b", 2, 2.0)])
    assert capsys.readouterr().out.splitlines() == [t.header(), t.row("a", 1, 1.0), t.row("b", 2, 2.0)]
