"""Command-line entry point ``rpr-cosim`` (also ``python -m cosim``).

Every verb's arguments are declared in :mod:`cosim.cli.grammar`; its handler lives in a module of
its own (``run_verb``, ``fmu_verb``...), imported only when the verb runs, and takes the parsed
arguments and returns an exit code.  A user mistake raises :class:`UserError` (or one of
the domain errors of :func:`cosim.errors.user_error_types`) and is printed as one line, never as
a traceback.
Options that several verbs share are declared once in :mod:`cosim.cli.options`; what the verbs
share while they run (messages on stderr, a file's problems, loading a scene) is in
:mod:`cosim.cli.verb`.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence

from ..errors import user_error_types
from .grammar import add_verbs
from .verb import interrupted
from ..interrupts import exit_code, signals_as_interrupts


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rpr-cosim", description="3-RPR manipulator co-simulation workbench")
    parser.add_argument("--version", action="version", version=f"rpr-cosim {version()}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    add_verbs(sub)
    return parser


def handler(name: str) -> Callable[[argparse.Namespace], int]:
    """The verb handler ``name`` (``"run_verb:_run"``), its module imported now: a verb loads
    only what it runs."""
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), function)


def version() -> str:
    """The installed package's version (its metadata), else the source tree's ``pyproject.toml``."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("rpr-cosim")
    except PackageNotFoundError:
        import re
        from pathlib import Path

        text = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
        found = re.search(r'^version = "([^"]+)"', text, re.M)
        return found.group(1) if found else "unknown"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    try:
        with signals_as_interrupts():
            return int(handler(args.handler)(args) or 0)
    except KeyboardInterrupt as exc:
        print(f"rpr-cosim: {interrupted(exc)}", file=sys.stderr)
        return exit_code(exc)
    except user_error_types() as exc:
        print(f"rpr-cosim {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the machine's trouble, not a bug: a full disk, a read-only directory
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"rpr-cosim {args.verb}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
