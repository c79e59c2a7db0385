"""``vigproc plugins``: the estimators and profile sources installed as extensions.

Each extension is loaded (its module imported) to report whether it works; a broken
one is listed with the reason and never used (:mod:`vigproc.core.extensions`).
"""

from __future__ import annotations

import argparse
import json

from vigproc.core.methods import METHODS


def _status(ext) -> tuple[bool, str | None]:
    from vigproc.core.extensions import ExtensionError

    try:
        ext.load()
    except ExtensionError as exc:
        return False, str(exc)
    return True, None


def cmd_plugins(args: argparse.Namespace) -> int:
    from vigproc.core.extensions import GROUPS, discover

    rows = []
    for group in GROUPS:
        for ext in discover(group):
            ok, why = _status(ext)
            rows.append({**ext.to_dict(), "ok": ok, "error": why})
    broken = sum(not r["ok"] for r in rows)
    if args.json:
        print(json.dumps({"builtin_methods": list(METHODS), "builtin_profiles": ["auto", "estimate", "lensfun"],
                          "extensions": rows, "broken": broken}, indent=1))
    else:
        print(f"built-in methods: {', '.join(METHODS)}")
        print("built-in profiles: auto, estimate, lensfun, embedded, source:NAME (a profile source below), PATH of a profile file")
        for group, what in GROUPS.items():
            mine = [r for r in rows if r["group"] == group]
            print(f"{what} plugins ({group}): {len(mine) or 'none installed'}")
            for r in mine:
                dist = f"{r['distribution']} {r['version']}" if r["distribution"] else "?"
                use = ("--method " if group.endswith("estimators") else "--profile source:") + r["name"]
                state = f"ok, use {use}" if r["ok"] else f"BROKEN: {r['error']}"
                print(f"  {r['name']:<20} {r['target']}  [{dist}]  {state}")
    return 1 if broken and args.strict else 0


def add_arguments(sp: argparse.ArgumentParser) -> None:
    """``vigproc plugins``'s arguments (its summary: :data:`vigproc.frontends.cli.COMMANDS`)."""
    sp.add_argument("--json", action="store_true", help="print the list as JSON")
    sp.add_argument("--strict", action="store_true", help="exit 1 when an installed plugin is broken")
    sp.set_defaults(fn=cmd_plugins)
