"""Sub-commands declared in a table and built on demand.

A command line of a few dozen sub-commands spends most of its start-up building their
parsers (argparse objects, and the modules that declare them). A :class:`Command` names
its one-line summary and the function that declares its arguments; :func:`add_commands`
lists every command of a table by name and summary (what ``--help`` shows) and builds
the arguments of only the command the command line names. ``vigproc`` and ``vigproc bench``
(the checkout's ``benchmarks/``) both declare their commands this way.
"""

from __future__ import annotations

import argparse
import importlib
from dataclasses import dataclass
from typing import Callable, Collection, Mapping, Sequence

__all__ = ["Command", "add_commands", "chosen_command", "command_parser", "resolve"]


@dataclass(frozen=True)
class Command:
    """One sub-command of a table.

    Parameters
    ----------
    help : str
        The one line ``PROG --help`` lists it with.
    arguments : str
        ``"module:function"``: the function (in the table's package) that declares the
        command's arguments on the parser it is given (and its ``fn``, description,
        epilog; see :func:`add_commands`).
    add_help : bool
        Whether argparse gives it ``-h``/``--help`` (a command that hands its arguments on
        declares its own).
    """

    help: str
    arguments: str
    add_help: bool = True


def resolve(spec: str, package: str) -> Callable:
    """The function ``"module:function"`` names, ``module`` in ``package``.

    Parameters
    ----------
    spec : str
    package : str
        Dotted package name, e.g. ``vigproc.frontends.commands``.

    Returns
    -------
    callable
    """
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(f"{package}.{module}"), name)


def chosen_command(argv: Sequence[str], takes_value: frozenset[str] = frozenset()) -> str | None:
    """The sub-command an argument list names: its first word that is not an option.

    Parameters
    ----------
    argv : sequence of str
        The arguments after the program's name.
    takes_value : frozenset of str
        The program's own options that take a value (the word after them is skipped).

    Returns
    -------
    str or None
        None when there is none (``--help``, or nothing).
    """
    skip = False
    for word in argv:
        if skip:
            skip = False
        elif word == "--":
            continue
        elif word.startswith("-"):
            skip = word in takes_value
        else:
            return word
    return None


def add_commands(subparsers: argparse._SubParsersAction, table: Mapping[str, Command], package: str,  # noqa: SLF001
                 build: Collection[str]) -> None:
    """Add ``table``'s commands to ``subparsers``, in the table's order.

    Every command gets its parser and its line in the help; only the commands in
    ``build`` get their arguments, declared by calling their :attr:`Command.arguments`
    function with the parser (which may also set its ``description``, ``epilog`` and
    ``formatter_class``: argparse reads them when it prints the help).

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
    table : mapping of str to Command
    package : str
        The package :attr:`Command.arguments` specs are in.
    build : collection of str
        The commands to build: the one a command line names (:func:`chosen_command`),
        none for the list alone, or all of them.
    """
    for name, command in table.items():
        full = name in build
        sp = subparsers.add_parser(name, help=command.help, add_help=full and command.add_help)
        if full:
            resolve(command.arguments, package)(sp)


def command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub-)parser of the command ``args`` were parsed for (``vigproc profile show``'s,
    say), so that a usage error is said with that command's usage line.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The top-level parser.
    args : argparse.Namespace
        What it parsed.

    Returns
    -------
    argparse.ArgumentParser
    """
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its sub-commands there
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            name = getattr(args, action.dest, None)
            if name in action.choices:
                return command_parser(action.choices[name], args)
    return parser
