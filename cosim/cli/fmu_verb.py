"""``rpr-cosim fmu``: build co-simulation FMUs from the model catalog and list the cache.

    rpr-cosim fmu build MODEL | FILE.mo:CLASS | FILE.py:MODEL [--fidelity F] [--set name=value ...] [--fmi 2|3] [--out DIR] [--cache DIR]
    rpr-cosim fmu list [--cache DIR]
    rpr-cosim fmu check FMU
    rpr-cosim fmu show MODEL[/FIDELITY] | FILE.fmu | FILE.mo:CLASS | FILE.py:MODEL [--markdown [FILE]]
    rpr-cosim fmu show --readme [README.md]

``build`` prints the FMU's path on stdout (progress goes to stderr).  ``--set`` values that are
numbers and name a parameter of the block override its default (the FMU's start value); any
other ``--set`` is a construction option of ``models.blocks.make`` (e.g. ``config=cross_leg``).
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from ..errors import UserError
from .verb import tagged
import fmus
from ..scenario.user_blocks import UserBlockError, user_block
from ..slaves.archive import archive_problem
from ..slaves.plan import run_plan
from ..analysis import model_doc
from ..slaves.behaviour import check_in_subprocess


def _blocks():
    try:
        import models.blocks as blocks
    except ModuleNotFoundError as exc:
        if exc.name in ("models.blocks",):
            raise UserError("the model catalog (models.blocks) is not installed in this build") from None
        raise
    return blocks


def _parse_sets(items: list[str]) -> tuple[dict[str, str], dict[str, int | float]]:
    """Split ``NAME=VALUE`` items into words and numbers (int when the text is a whole number)."""
    words: dict[str, str] = {}
    numbers: dict[str, int | float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name or not value:
            raise UserError(f"--set {item!r}: expected NAME=VALUE, e.g. --set Kp=30 or --set config=cross_leg")
        for kind in (int, float):
            try:
                numbers[name] = kind(value)
                break
            except ValueError:
                continue
        else:
            words[name] = value
    return words, numbers


def _is_user_block(what: str) -> bool:
    """``FILE.mo:CLASS`` or ``FILE.py:MODEL``: a user's block."""
    return ":" in what and Path(what.rpartition(":")[0]).suffix in (".mo", ".py")


def _build(args: argparse.Namespace) -> int:
    if _is_user_block(args.model):
        return _build_user(args)
    blocks = _blocks()
    catalog = blocks.catalog()
    if args.model not in catalog:
        raise UserError(f"unknown model {args.model!r}; expected one of {', '.join(sorted(catalog))}")
    if args.fidelity is not None and args.fidelity not in catalog[args.model]:
        raise UserError(f"model {args.model!r} has no fidelity {args.fidelity!r}; expected one of "
                        f"{', '.join(catalog[args.model])}")
    words, numbers = _parse_sets(args.sets)
    block = blocks.make(args.model, args.fidelity, **words)
    names = {p.name for p in block.params}
    overrides = {k: v for k, v in numbers.items() if k in names}
    options = {k: v for k, v in numbers.items() if k not in names}
    if options:  # numeric construction options: let make() judge them
        block = blocks.make(args.model, args.fidelity, **words, **options)
    return _deliver(block, overrides, args)


def _deliver(block, overrides: dict[str, int | float], args: argparse.Namespace) -> int:
    """Build ``block`` with its parameter ``overrides`` (or fetch it from the cache), copy the FMU
    to ``--out`` if asked; print its path."""

    path = fmus.build_fmu(block, fmi_version=args.fmi + ".0", cache_dir=args.cache, params=overrides,
                          progress=tagged("fmu"))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        dest = args.out / path.name
        shutil.copyfile(path, dest)
        path = dest
    print(path)
    return 0


def _build_user(args: argparse.Namespace) -> int:
    """``fmu build FILE.mo:CLASS`` / ``FILE.py:MODEL``: a user's block, built and cached like ours."""

    if args.fidelity is not None:
        raise UserError("--fidelity: name a Python block's fidelity as FILE.py:MODEL/FIDELITY; a Modelica class has one")
    words, numbers = _parse_sets(args.sets)
    try:
        block, _, opts = user_block(args.model, **words)
        names = {o[0] for o in opts}
        if any(k in names for k in numbers):  # numeric construction options (substeps...)
            block, _, _ = user_block(args.model, **words, **{k: v for k, v in numbers.items() if k in names})
    except UserBlockError as exc:
        raise UserError(str(exc)) from None
    overrides = {k: v for k, v in numbers.items() if k not in names}
    return _deliver(block, overrides, args)


def _list(args: argparse.Namespace) -> int:

    try:
        catalog = _blocks().catalog()
    except UserError as exc:
        print(f"catalog: {exc}")
    else:
        print("catalog:")
        for model in sorted(catalog):
            print(f"  {model:<14} {', '.join(catalog[model])}")
    rows = fmus.cached_fmus(args.cache)
    print(f"cached FMUs in {fmus.cache_root(args.cache)}: {len(rows)}")
    if rows:
        print(f"  {'model identifier':<24} {'FMI':>3} {'integrator':<10} {'states':>6} {'build s':>7}  file")
        for path, rec in rows:
            print(f"  {rec.get('model_identifier', path.stem):<24} {rec.get('fmi_version', '?'):>3} "
                  f"{rec.get('integrator', '?'):<10} {rec.get('states', '?'):>6} "
                  f"{rec.get('total_s', float('nan')):>7.2f}  {path}")
    return 0


def _check(args: argparse.Namespace) -> int:
    from fmpy.validation import validate_fmu


    if not args.fmu.is_file():
        raise UserError(f"{args.fmu}: no such FMU file")
    problem = archive_problem(args.fmu)
    if problem:
        raise UserError(f"{args.fmu}: {problem}")
    try:
        problems = validate_fmu(str(args.fmu))
    except Exception as exc:  # fmpy raises bare Exceptions for malformed XML
        raise UserError(f"{args.fmu}: cannot read the model description ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    for p in problems:
        print(p)
    n = len(problems)

    try:
        plan, departures = run_plan(args.fmu)
    except UserError as exc:
        plan, departures = [], [str(exc)]
    for line in plan:
        print(f"{args.fmu}: a run: {line}")
    for line in departures:
        print(f"{args.fmu}: {line}")
    n += len(departures)
    if args.behaviour:

        found = check_in_subprocess(args.fmu)
        for line in found["departures"]:
            print(line)
        fixes = [k for k, v in found["workarounds"].items() if v]
        print(f"{args.fmu}: behaviour: {len(found['departures'])} departure(s) in {len(found['checks'])} checks "
              f"({', '.join(found['checks'])}); skipped: "
              f"{'; '.join(f'{k} ({v})' for k, v in found['skipped'].items()) or 'none'}; "
              f"workarounds a run applies: {', '.join(fixes) or 'none'}", file=sys.stderr)
        n += len(found["departures"])
    print(f"{args.fmu}: {n} problem(s)", file=sys.stderr)
    return min(n, 100)


def _show(args: argparse.Namespace) -> int:

    if args.readme is not None:
        changed = model_doc.update_readme(args.readme)
        print(f"{args.readme}: model section {'rewritten' if changed else 'already up to date'}")
        return 0
    if not args.what:
        raise UserError("fmu show: name a model (e.g. pid/continuous) or an FMU file, or pass --readme")
    if _is_user_block(args.what):
        info = model_doc.user_block_info(args.what)
    elif args.what.endswith(".fmu") or Path(args.what).is_file():
        info = model_doc.fmu_info(Path(args.what))
    else:
        model, _, fidelity = args.what.partition("/")
        info = model_doc.model_info(model, fidelity or None)
    if args.markdown is None:
        sys.stdout.write(model_doc.text(info))
    elif args.markdown == "-":
        sys.stdout.write(model_doc.markdown(info, level=1))
    else:
        Path(args.markdown).write_text(model_doc.markdown(info, level=1))
        print(args.markdown)
    return 0
