"""Command-line entry point ``rpr-cosim`` (also ``python -m cosim``).

Each verb lives in its own module exposing ``register(subparsers)``; the verb's handler takes the
parsed arguments and returns an exit code.  A user mistake raises :class:`UserError` (or one of
the domain errors listed in ``_USER_ERRORS``) and is printed as one line, never as a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from .errors import user_error_types

#: Modules that contribute verbs, in the order they appear in ``--help``.
VERB_MODULES = ("cosim.cmd_analyze", "cosim.cmd_fmu", "cosim.cmd_run", "cosim.cmd_compare", "cosim.cmd_study",
                "cosim.cmd_ssp")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rpr-cosim", description="3-RPR manipulator co-simulation workbench")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for name in VERB_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # verb not installed in this build
            raise
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print("rpr-cosim: interrupted", file=sys.stderr)
        return 130
    except user_error_types() as exc:
        print(f"rpr-cosim {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
