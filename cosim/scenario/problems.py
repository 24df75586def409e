"""Findings of validation (:class:`Problem`), the error listing them all (:class:`SceneError`) and
the closest-name hint every message uses."""
from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from ..errors import UserError


Loc = tuple[str, int]  # (file, line); line 0 = no line (a --set override)


@dataclass(frozen=True)
class Problem:
    """One finding of validation: where, what, and how bad."""

    file: str
    line: int
    message: str
    severity: str = "error"

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line else self.file
        return f"{where}: {self.severity}: {self.message}"


class SceneError(UserError):
    """A scene that cannot run; :attr:`problems` lists every error (and warning) found."""

    def __init__(self, problems: Sequence[Problem]):
        self.problems = list(problems)
        errors = [p for p in self.problems if p.severity == "error"]
        super().__init__("\n".join(str(p) for p in errors) or "invalid scene")


def suggest(name: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices`` (difflib), else ``""``."""
    close = difflib.get_close_matches(str(name), list(choices), n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else ""
