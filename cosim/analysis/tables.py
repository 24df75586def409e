"""Text tables of results (per-variable errors, batch rows, per-slave costs, the design
tables), laid out by rich: columns sized to their cells, numbers right-aligned, no colours and
no control characters, so a table reads the same on a terminal, in a pipe or a log and in a
notebook cell.  The cells arrive formatted (each caller knows its units and precision)."""
from __future__ import annotations

import io
from collections.abc import Sequence

from rich.console import Console
from rich.table import Table


def text_table(columns: Sequence[str], rows: Sequence[Sequence[str]], *, right: Sequence[bool] | None = None,
               indent: int = 2, rules: bool = False) -> str:
    """``rows`` of text cells under ``columns`` as aligned text: a column is right-aligned where
    ``right`` says so (default: all but the first); every line starts with ``indent`` blanks;
    ``rules`` draws a line under the header (and above and below the table)."""
    right = list(right) if right is not None else [k > 0 for k in range(len(columns))]
    table = Table(box=None, show_header=True, header_style=None, pad_edge=False, padding=(0, 2, 0, 0), expand=False)
    for name, r in zip(columns, right):
        table.add_column(name, justify="right" if r else "left", no_wrap=True)
    for row in rows:
        table.add_row(*[str(c) for c in row])
    buf = io.StringIO()
    Console(file=buf, width=100_000, color_system=None, force_terminal=False, force_jupyter=False,
            legacy_windows=False, emoji=False, highlight=False, markup=False).print(table)
    lines = [ln.rstrip() for ln in buf.getvalue().splitlines() if ln.strip()]
    if rules:
        rule = "-" * max(map(len, lines))
        lines = [rule, lines[0], rule, *lines[1:], rule]
    return "\n".join(" " * indent + ln for ln in lines)
