"""Quoted command outputs in the documentation's pages, compared with what the command prints.

A quoted output is a fenced ``text`` block whose first line is ``$ COMMAND``; the lines below it
are the command's printed output, whole or in part (a line ``...`` marks an elision).  A quoted
line matches a printed one when their words are the same and each number is within one unit of
its last printed digit, after both are :func:`normalised` (wall times, real-time factors, the
doStep table's timings and scene hashes differ from one run to the next and are not compared).
``benchmarks/figures.py --check`` and ``python -m docgen.tutorial`` use these.
"""
from __future__ import annotations

import re
from pathlib import Path

#: A number as printed: optional sign, thousands separators, decimals, exponent.
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w])")

#: What differs between two runs of one command and is not a figure the docs vouch for.
_VOLATILE = [
    (re.compile(r"\[[0-9a-f]{12}\]"), "[HASH]"),  # a scene hash
    (re.compile(r"\b(in|build|init|generation|compile|ok,|took|wall) [-+]?\d[\d.]*(?:e[-+]?\d+)? (s|ms)\b"),
     r"\1 T \2"),  # wall times
    (re.compile(r"real-time factor [\d.e+-]+"), "real-time factor T"),
    (re.compile(r"(\s+\d+)\s+[\d.]+\s+[\d.]+\s+[\d.]+%\s*$"), r"\1 T T T%"),  # a doStep row: calls, ms, us, share
    (re.compile(r"^(\s*master)\s+[\d.]+\s+[\d.]+\s+[\d.]+%\s*$"), r"\1 T T T%"),  # the master's own row
]


def normalised(line: str) -> str:
    """``line`` with its volatile parts (module docstring) replaced by placeholders."""
    for pattern, repl in _VOLATILE:
        line = pattern.sub(repl, line)
    return line.rstrip()


def quoted_blocks(page: Path) -> list[tuple[int, str, list[str], bool]]:
    """(line of the first quoted line, the command, the quoted output lines, whether a 'Printed
    on' date line stands just above the block) for every quoted command output in ``page``."""
    lines = page.read_text().splitlines()
    found = []
    for i, line in enumerate(lines):
        if line.strip() == "```text" and i + 1 < len(lines) and lines[i + 1].startswith("$ "):
            command = " ".join(lines[i + 1][2:].split())
            body = []
            for ln in lines[i + 2:]:
                if ln.strip().startswith("```"):
                    break
                body.append(ln)
            dated = any("rinted on" in ln for ln in lines[max(0, i - 3):i])
            found.append((i + 3, command, body, dated))
    return found


def last_digit(token: str) -> float:
    """One unit of the last printed digit of a number as text (``1.339e-05`` -> 1e-08)."""
    mant, _, exp = token.lower().replace(",", "").partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 10.0 ** (-decimals + (int(exp) if exp else 0))


def skeleton(line: str) -> str:
    """The line's words with every number replaced by ``#`` (what must stay equal)."""
    return " ".join(NUMBER.sub("#", normalised(line)).split())


def same_figures(quoted: str, now: str) -> bool:
    """The same line, or the same words with each number within one unit of its last printed
    digit (a figure rounded at a tie may print either way from one build to the next)."""
    quoted, now = normalised(quoted), normalised(now)
    if quoted == now:
        return True
    if quoted[:len(quoted) - len(quoted.lstrip())] != now[:len(now) - len(now.lstrip())]:
        return False  # another indentation: another level of the output
    if skeleton(quoted) != skeleton(now):
        return False
    for x, y in zip(NUMBER.findall(quoted), NUMBER.findall(now)):
        if x != y and abs(float(x.replace(",", "")) - float(y.replace(",", ""))) > 1.0001 * last_digit(x):
            return False
    return True


def drifted(body: list[str], printed: list[str]) -> list[tuple[int, str, str]]:
    """The quoted lines of ``body`` that the printed lines do not contain, in order: (index in
    ``body``, the quoted line, the closest printed line: same words if any, else most characters
    in common).  ``...`` lines and blank lines are elisions."""
    out, start = [], 0
    for k, line in enumerate(body):
        if not line.strip() or line.strip() in ("...", "…"):
            continue
        hit = next((j for j in range(start, len(printed)) if same_figures(line, printed[j])), None)
        if hit is None:  # out of order, or gone: the closest line anywhere
            hit_any = next((j for j in range(len(printed)) if same_figures(line, printed[j])), None)
            if hit_any is not None:
                continue
            shape = skeleton(line)
            close = next((p for p in printed[start:] + printed[:start] if skeleton(p) == shape), None)
            if close is None:
                close = max(printed, key=lambda p: sum(a == b for a, b in zip(p, line)), default="")
            out.append((k, line, close))
        else:
            start = hit + 1
    return out
