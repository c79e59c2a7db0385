"""The command table (vigproc.frontends.cli.COMMANDS, benchmarks.cli.BENCHMARKS): ``--help``
lists every command without building any; a command's parser is built when it is named,
with the options its table entry declares, and its ``--help`` says them all."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from benchmarks import cli as bench_cli
from vigproc.frontends import cli
from vigproc.frontends.commands._subcommands import chosen_command


def _option_sets(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], set[str]]:
    """Every (sub-)parser's option strings and positional names, by command path."""
    out = {path: set()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.update(_option_sets(sub, (*path, name)))
            out[path].add("{" + ",".join(action.choices) + "}")
        else:
            out[path].update(action.option_strings or [action.dest])
    return out


def _help(main, argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 0, capsys.readouterr().err
    return capsys.readouterr().out


def test_the_top_level_help_lists_every_command_and_builds_none(capsys):
    parser = cli.build_parser(["--help"])
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert list(sub.choices) == list(cli.COMMANDS)
    assert all(len(p._actions) == 0 for p in sub.choices.values())  # listed, not built (no -h even)
    text = _help(cli.main, ["--help"], capsys)
    for name, command in cli.COMMANDS.items():
        assert name in text and " ".join(command.help.split()[:4]) in " ".join(text.split())


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_a_commands_help_says_every_option_its_table_entry_declares(name, capsys):
    """The parser built for ``vigproc NAME`` alone is the full parser's NAME, option for
    option, down to its sub-commands; ``vigproc NAME [SUB] --help`` lists them all."""
    full = {k: v for k, v in _option_sets(cli.build_parser()).items() if k[:1] == (name,)}
    alone = {k: v for k, v in _option_sets(cli.build_parser([name])).items() if k[:1] == (name,)}
    assert alone == full and full[(name,)]
    if name == "bench":
        return  # its help is the benchmarks' (below)
    for path, options in full.items():
        text = _help(cli.main, [*path, "--help"], capsys)
        assert text.startswith(f"usage: vigproc {' '.join(path)}")
        for option in options - {"fn"}:
            if option.startswith("-") or option.startswith("{"):
                assert option in text, (path, option)


@pytest.mark.parametrize("name", list(bench_cli.BENCHMARKS))
def test_a_benchmarks_help_says_every_option_its_table_entry_declares(name, capsys):
    full = _option_sets(bench_cli.build_parser())[(name,)]
    assert _option_sets(bench_cli.build_parser([name]))[(name,)] == full
    text = " ".join(_help(cli.main, ["bench", name, "--help"], capsys).split())  # argparse wraps long choices
    assert text.startswith(f"usage: vigproc bench {name}")
    for option in full:
        if option.startswith("-"):
            assert option in text, option


def test_the_bench_help_lists_every_benchmark(capsys):
    text = _help(cli.main, ["bench", "--help"], capsys)
    for name in bench_cli.BENCHMARKS:
        assert f"\n    {name} " in text or f"\n    {name}\n" in text, name


def test_the_chosen_command_is_the_first_word_not_an_option():
    assert chosen_command(["-v", "-v", "correct", "--help"]) == "correct"
    assert chosen_command(["--help"]) is None and chosen_command([]) is None
    assert chosen_command(["--", "estimate"]) == "estimate"
    assert chosen_command(["--benchmarks-dir", "clean", "io"], frozenset({"--benchmarks-dir"})) == "io"


def test_an_unknown_command_is_a_usage_error_listing_them(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["corect", "x.jpg"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "invalid choice: 'corect'" in err and "estimate" in err


@pytest.mark.parametrize("argv, loaded, not_loaded", [
    (["--help"], [], ["watch", "hook", "batch", "check", "_parsers", "_bench"]),
    (["watch", "--help"], ["watch"], ["hook", "batch", "check", "_parsers", "correct"]),
    (["correct", "--help"], ["_parsers"], ["watch", "hook", "correct", "profile"]),
])
def test_help_imports_only_the_command_asked_about(argv, loaded, not_loaded):
    """A fresh process: ``vigproc --help`` loads no command module, ``vigproc CMD --help``
    only the one declaring CMD's arguments (not its handler's, when they differ)."""
    code = (
        "import sys\n"
        "from vigproc.frontends.cli import main\n"
        "try:\n"
        f"    main({argv!r})\n"
        "except SystemExit:\n"
        "    pass\n"
        "print(sorted(m.rpartition('.')[2] for m in sys.modules if m.startswith('vigproc.frontends.commands.')),"
        " file=sys.stderr)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    modules = eval(r.stderr.strip().splitlines()[-1])  # noqa: S307 - our own child's list of names
    for m in loaded:
        assert m in modules, modules
    for m in not_loaded:
        assert m not in modules, modules


def test_python_dash_m_vigproc_is_the_command(tmp_path):
    """``python -m vigproc`` runs the ``vigproc`` command (where the scripts folder is not on
    PATH), with its exit codes: a missing input is a failed file (4), not a traceback."""
    r = subprocess.run([sys.executable, "-m", "vigproc", "correct", str(tmp_path / "missing.jpg"), "-o",
                        str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 4, r.stderr
    assert "file not found" in r.stderr and "Traceback" not in r.stderr
