"""The base of scene validation: where problems are collected, and the checks every part uses."""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .problems import Loc, Problem, suggest
from .yamlfile import YMap


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class Checker:
    """Collects :class:`Problem` s while the checks of the mixins walk a scene tree."""

    def __init__(self, tree: YMap, path: Path | None, catalog):
        self.tree, self.path, self.catalog = tree, path, catalog
        self.problems: list[Problem] = []
        #: components declared but refused (their problem already reported): a connection to one
        #: is not reported again as an unknown component
        self.refused: set[str] = set()

    def err(self, where: Loc, msg: str) -> None:
        self.problems.append(Problem(where[0], where[1], msg))

    def warn(self, where: Loc, msg: str) -> None:
        self.problems.append(Problem(where[0], where[1], msg, "warning"))

    def note(self, where: Loc, msg: str) -> None:
        """What the check found out or assumed (shown with the run, kept in its sidecar)."""
        self.problems.append(Problem(where[0], where[1], msg, "note"))

    def number(self, node: YMap, key: str, what: str, *, required: bool = False, default=None):
        if key not in node:
            if required:
                self.err(node.where, f"{what} is missing; expected a number in seconds")
            return default
        v = node[key]
        if not _is_number(v) or not math.isfinite(v):
            self.err(node.loc(key), f"{what} = {v!r} is not a finite number")
            return None
        return float(v)

    def unknown_keys(self, node: YMap, allowed: Sequence[str], what: str) -> None:
        for k in node:
            if k not in allowed:
                self.err(node.loc(k), f"unknown key {k!r} in {what}{suggest(str(k), allowed)} "
                                      f"(expected: {', '.join(allowed)})")

    # components ---------------------------------------------------------------------------------
