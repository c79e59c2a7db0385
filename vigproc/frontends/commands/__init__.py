"""Sub-commands of ``vigproc`` that live in their own modules.

Each module here exposes ``register(subparsers)``, which adds its parser(s) and sets
``fn`` to a callable taking the parsed ``argparse.Namespace`` and returning an exit
code.  A module may also expose ``register_bench(bench_subparsers)`` to add a
``vigproc bench NAME`` benchmark.  :func:`vigproc.frontends.cli.build_parser` registers every
module found here.
"""
