"""The handlers of ``vigproc``'s commands, one module per command (or family).

:data:`vigproc.frontends.cli.COMMANDS` names, for each command, the function declaring
its arguments (``add_arguments`` in its module, or :mod:`._parsers` for the commands
whose handler modules load the numeric stack); that function sets the parser's ``fn``
to the handler, a function taking the parsed ``argparse.Namespace`` and returning an
exit code. Modules with a leading underscore hold what several commands share.
"""
