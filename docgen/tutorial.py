"""Run docs/tutorial.md as a reader would and compare its quoted outputs with what its commands
print (:mod:`docgen.quoted`: numbers within their last printed digit, wall times and hashes
normalised).

    python -m docgen.tutorial            # the cheap steps (~1 min): report drifted quotes, exit 1 if any
    python -m docgen.tutorial --all      # also the expensive steps (multibody, fidelity study, batch)
    python -m docgen.tutorial --update   # rewrite the drifted quoted lines (same words, new figures) and dates

The commands run in a temporary copy of ``scenarios/``, in the page's order, in this process
(``cosim.cli.main``), with the FMU cache ``$RPR_COSIM_CACHE`` (or ``--cache``).  A YAML block the
page asks to save (``Save this as `NAME```, or ``(`NAME`)`` just above it) is written first.
Commands of the rig (``board``, ``*_hil``) need a second terminal and are never run.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import os
import re
import shlex
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .quoted import drifted, quoted_blocks, skeleton

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "tutorial.md"
#: Commands that take minutes (a multibody build, 18 combinations, 25 runs): run with ``--all``.
EXPENSIVE = ("fidelity=multibody", "runs/multibody", "study fidelity", "batch ")
#: Commands that need the rig or a second terminal: never run here.
MANUAL = ("board ", "_hil")
_SAVE = re.compile(r"(?:[Ss]ave (?:this|it) as|\()\s*`([\w./-]+\.ya?ml)`")


@dataclass
class Step:
    kind: str  # "save" or "run"
    text: str  # the file's content or the command
    name: str = ""  # the file to save


def steps(page: Path = PAGE) -> list[Step]:
    """The page's files to save and its ``rpr-cosim`` commands, in order."""
    out: list[Step] = []
    lines = page.read_text().splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"^```(\w*)", lines[i])
        if not fence:
            i += 1
            continue
        j = next(k for k in range(i + 1, len(lines)) if lines[k].startswith("```"))
        body = lines[i + 1:j]
        if fence.group(1) == "yaml":
            before = " ".join(lines[max(0, i - 3):i])
            m = None
            for m in _SAVE.finditer(before):
                pass
            if m:
                out.append(Step("save", "\n".join(body) + "\n", m.group(1)))
        elif fence.group(1) == "bash":
            for cmd in " ".join(ln[:-1] if ln.endswith("\\") else ln + "\n" for ln in body).splitlines():
                words = shlex.split(cmd, comments=True)
                if words and words[0].endswith("rpr-cosim"):
                    out.append(Step("run", " ".join(["rpr-cosim", *words[1:]])))
        i = j + 1
    return out


def _quote_key(command: str) -> str:
    return " ".join(shlex.split(command.replace(".venv/bin/", ""), comments=True))


def run_steps(page: Path, work: Path, *, expensive: bool, cache: Path | None) -> dict[str, list[str]]:
    """Run the page's steps in ``work``; the printed lines (stdout then stderr, the work
    directory's path removed) of each command that ran, by command."""
    from cosim.cli import main

    printed: dict[str, list[str]] = {}
    old_cwd, old_cache = Path.cwd(), os.environ.get("RPR_COSIM_CACHE")
    if cache is not None:
        os.environ["RPR_COSIM_CACHE"] = str(cache)
    try:
        os.chdir(work)
        for step in steps(page):
            if step.kind == "save":
                (work / step.name).write_text(step.text)
                continue
            if any(m in step.text for m in MANUAL) or (not expensive and any(e in step.text for e in EXPENSIVE)):
                continue
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    code = main(shlex.split(step.text)[1:])
                except SystemExit as exc:
                    code = exc.code
            text = (out.getvalue() + err.getvalue()).replace(f"{work}/", "").replace(str(work), ".")
            printed[_quote_key(step.text)] = text.splitlines() + [f"(exit status {code})"]
    finally:
        os.chdir(old_cwd)
        if cache is not None:
            if old_cache is None:
                os.environ.pop("RPR_COSIM_CACHE", None)
            else:
                os.environ["RPR_COSIM_CACHE"] = old_cache
    return printed


def check(page: Path = PAGE, *, expensive: bool = False, cache: Path | None = None, update: bool = False,
          say=print) -> int:
    """Run the tutorial in a temporary copy of the scenes and report every quoted line its
    command no longer prints (with ``update``, rewrite it); returns the number of problems."""
    with tempfile.TemporaryDirectory(prefix="tutorial-") as tmp:
        work = Path(tmp)
        shutil.copytree(ROOT / "scenarios", work / "scenarios")
        printed = run_steps(page, work, expensive=expensive, cache=cache)
    lines = page.read_text().splitlines()
    problems = checked = rewritten = 0
    for lineno, command, body, dated in quoted_blocks(page):
        key = _quote_key(command)
        if key not in printed:
            say(f"{page.name}:{lineno - 1}: not run here ({'--all runs it' if key else 'not a step'}): {command}")
            continue
        checked += 1
        if not dated:
            problems += 1
            say(f"{page.name}:{lineno - 2}: the quoted output of `{command}` says not when it was printed")
        for k, line, close in drifted(body, printed[key]):
            problems += 1
            say(f"{page.name}:{lineno + k}: `{command}` no longer prints\n  page: {line}\n  now:  {close}")
            if update and close and skeleton(close) == skeleton(line):
                lines[lineno - 1 + k] = close
                rewritten += 1
        if update:
            for d in range(max(0, lineno - 6), lineno - 2):
                lines[d] = re.sub(r"rinted on \d{4}-\d\d-\d\d", f"rinted on {datetime.date.today()}", lines[d])
    if update:
        page.write_text("\n".join(lines) + "\n")
    say(f"tutorial: {checked} quoted outputs checked, {problems} problem{'s' if problems != 1 else ''}"
        + (f" ({rewritten} rewritten; the others changed their words: edit them by hand)"
           if update and problems > rewritten else " (rewritten)" if update and problems else ""))
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--all", action="store_true", help="also the expensive steps (minutes)")
    ap.add_argument("--update", action="store_true", help="rewrite the drifted quoted lines in the page")
    ap.add_argument("--cache", type=Path, help="FMU cache (default: $RPR_COSIM_CACHE or ~/.cache/rpr-cosim/fmus)")
    ap.add_argument("page", nargs="?", type=Path, default=PAGE)
    args = ap.parse_args(argv)
    return 1 if check(args.page, expensive=args.all, cache=args.cache, update=args.update) else 0


if __name__ == "__main__":
    sys.exit(main())
