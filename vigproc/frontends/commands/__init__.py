"""Sub-commands of ``vigproc`` that live in their own modules.

Each module here exposes ``register(subparsers)``, which adds its parser(s) and sets
``fn`` to a callable taking the parsed ``argparse.Namespace`` and returning an exit
code.  A module may also expose ``register_bench(bench_subparsers)`` to add a
``vigproc bench NAME`` benchmark.  :func:`vigproc.frontends.cli.build_parser` registers every
module found here, except the handler modules of the commands it declares itself
(``estimate``, ``correct``, ``profile``, ``prior``: :data:`vigproc.frontends.cli.HANDLER_MODULES`),
which are imported only to run their command and import what they need at their top.
"""
