"""The command-line options that several verbs share, each declared once.

Every function adds one named option (or a verb's sub-actions) to an ``argparse`` parser, with the
same destination, type, default and metavar wherever it appears; a verb passes its own help text
where the meaning differs from one verb to another.
"""
from __future__ import annotations

import argparse
from pathlib import Path

#: ``--cache``'s help where the verb names the default.
CACHE_HELP = "FMU cache directory (default $RPR_COSIM_CACHE or ~/.cache/rpr-cosim/fmus)"
#: The trace file formats a run writes (:mod:`cosim.trace`).
TRACE_FORMATS = ["csv", "commented-csv", "parquet", "npy"]

#: A verb's handler, ``"<module>:<function>"`` of :mod:`cosim.cli` (``"run_verb:_run"``), taking the
#: parsed arguments and returning an exit code; imported when the verb runs (:func:`cosim.cli.handler`).
Handler = str


def add_actions(sub: argparse._SubParsersAction, name: str, dest: str, metavar: str = "ACTION",
                **kw: str) -> argparse._SubParsersAction:
    """The verb ``name`` with required sub-actions (``fmu build``, ``study precision``...); ``kw``
    are the verb's ``help`` and ``description``."""
    p = sub.add_parser(name, **kw)
    actions = p.add_subparsers(dest=dest, metavar=metavar)
    actions.required = True
    return actions


def add_verb(sub: argparse._SubParsersAction, name: str, handler: Handler, **kw: str) -> argparse.ArgumentParser:
    """The verb (or sub-action) ``name`` run by ``handler`` (``"run_verb:_run"``: ``_run(args) -> exit
    code`` of :mod:`cosim.cli.run_verb`); ``kw`` are its ``help`` and ``description``."""
    p = sub.add_parser(name, **kw)
    p.set_defaults(handler=handler)
    return p


def add_scene(p: argparse.ArgumentParser, help: str = "scene file, e.g. scenarios/pid_step.yaml") -> None:
    """The positional scene file."""
    p.add_argument("scene", type=Path, help=help)


def add_sets(p: argparse.ArgumentParser, help: str, metavar: str = "PATH=VALUE") -> None:
    """``--set``, repeatable, into ``args.sets`` (scene overrides, or a block's parameters)."""
    p.add_argument("--set", dest="sets", action="append", default=[], metavar=metavar, help=help)


def add_out(p: argparse.ArgumentParser, help: str, *short: str) -> None:
    """``--out`` (and its ``short`` spellings such as ``-o``): where the verb writes."""
    p.add_argument(*short, "--out", type=Path, help=help)


def add_cache(p: argparse.ArgumentParser, help: str = CACHE_HELP) -> None:
    """``--cache``: the FMU cache directory (:mod:`fmus.cache`)."""
    p.add_argument("--cache", type=Path, help=help)


def add_trace_format(p: argparse.ArgumentParser, help: str, default: str = "csv") -> None:
    """``--format`` of the trace files, into ``args.trace_format``."""
    p.add_argument("--format", dest="trace_format", choices=TRACE_FORMATS, default=default, help=help)


def add_report(p: argparse.ArgumentParser, help: str) -> None:
    """``--report``: also write the interactive HTML report (:mod:`cosim.analysis.html_report`)."""
    p.add_argument("--report", action="store_true", help=help)


def add_only(p: argparse.ArgumentParser, help: str = "compare only these signals", metavar: str = "GLOB") -> None:
    """``--only``, repeatable: the signals (glob patterns) a comparison covers."""
    p.add_argument("--only", action="append", default=[], metavar=metavar, help=help)


def add_tol(p: argparse.ArgumentParser, help: str, default: float | None = 1e-3) -> None:
    """``--tol``: a relative tolerance (error relative to each signal's range)."""
    p.add_argument("--tol", type=float, default=default, metavar="REL", help=help)


def add_variants(p: argparse.ArgumentParser, help: str) -> None:
    """``--variant``, repeatable: master algorithm variants ``ALG/INPUTS`` to study."""
    p.add_argument("--variant", action="append", default=[], metavar="ALG/INPUTS", help=help)
