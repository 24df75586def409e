"""What the verbs share while they run: messages on stderr, a file's problems, loading a scene.

Results go to stdout; progress, notes and problems to stderr, one line each.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from ..scenario import load
from ..study.fidelity import resolve_auto


def say(msg: object, flush: bool = False) -> None:
    """One line on stderr."""
    print(msg, file=sys.stderr, flush=flush)


def tagged(tag: str) -> Callable[[str], None]:
    """A progress callback that prints ``[tag] message`` on stderr (``[fmu]`` for FMU builds)."""
    return lambda msg: say(f"[{tag}] {msg}")


def interrupted(exc: BaseException) -> str:
    """``interrupted`` or ``interrupted by SIGTERM``: what stopped the verb (:mod:`cosim.interrupts`)."""
    return f"interrupted{' by ' + str(exc) if str(exc) else ''}"


def refuse(exc: Exception, verb: str, path: Path, outcome: str = "nothing was run", count: bool = True) -> int:
    """Print the problems of a scene or batch file (``exc.problems``, one a line) and the line
    that closes them; return the exit code of a user mistake, 2."""
    for p in exc.problems:
        say(str(p))
    n = sum(p.severity == "error" for p in exc.problems)
    counted = f"{n} problem{'s' if n != 1 else ''}; " if count else ""
    say(f"rpr-cosim {verb}: {path}: {counted}{outcome}")
    return 2


def load_scene(args: argparse.Namespace):
    """The scene of ``args.scene`` with the ``--set`` overrides of ``args.sets`` (``fidelity: auto``
    resolved by the fidelity study); raises :class:`cosim.scenario.SceneError`."""

    return load(args.scene, args.sets, auto_fidelity=resolve_auto)
