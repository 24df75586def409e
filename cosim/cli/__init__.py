"""Command-line entry point ``rpr-cosim`` (also ``python -m cosim``).

Each verb lives in its own module exposing ``register(subparsers)``; the verb's handler takes the
parsed arguments and returns an exit code.  A user mistake raises :class:`UserError` (or one of
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
from collections.abc import Sequence

from ..errors import user_error_types
from .verb import interrupted

#: Modules that contribute verbs, in the order they appear in ``--help``.
VERB_MODULES = ("cosim.cli.analyze", "cosim.cli.fmu", "cosim.cli.run", "cosim.cli.compare", "cosim.cli.fit",
                "cosim.cli.study", "cosim.cli.ssp", "cosim.cli.board", "cosim.cli.batch", "cosim.cli.report",
                "cosim.cli.design", "cosim.cli.task")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rpr-cosim", description="3-RPR manipulator co-simulation workbench")
    parser.add_argument("--version", action="version", version=f"rpr-cosim {version()}")
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
    from ..interrupts import exit_code, signals_as_interrupts

    try:
        with signals_as_interrupts():
            return int(args.handler(args) or 0)
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
