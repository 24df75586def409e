"""Progress bars by tqdm, for terminals, pipes and notebooks alike.

On a terminal the bar is redrawn in place; written to a pipe or a file (a CI log, ``2> log``)
it becomes whole lines, at most one every ``pipe_every_s`` seconds, with no carriage return and
no escape sequence; in a Jupyter notebook it is tqdm's widget (``tqdm.auto``).  Runs use
:func:`progress_bar` (a ``progress(done, total)`` callback), batches
:class:`cosim.batch.overview.Progress`, both through :func:`bar`.
"""
from __future__ import annotations

import sys
from collections.abc import Callable

#: Seconds between two lines of a bar written to a pipe or a file.
PIPE_EVERY_S = 5.0


class _Lines:
    """A stream for tqdm that turns its in-place redraws into whole lines (for pipes and logs)."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").replace("\x1b[A", "")
        if text.strip():
            self.stream.write(text.rstrip() + "\n")

    def flush(self) -> None:
        self.stream.flush()


def in_notebook() -> bool:
    """Whether this process is a Jupyter kernel (where tqdm draws a widget)."""
    shell = getattr(sys.modules.get("IPython"), "get_ipython", lambda: None)()
    return type(shell).__name__ == "ZMQInteractiveShell"


def bar(total: int, desc: str, *, unit: str = "it", stream=None, delay: float = 0.0, initial: int = 0):
    """A tqdm bar of ``total`` items on ``stream`` (default stderr), shown after ``delay`` seconds."""
    stream = stream or sys.stderr
    common = {"total": total, "desc": desc, "unit": unit, "delay": delay, "initial": initial, "leave": True}
    if stream is sys.stderr and in_notebook():
        from tqdm.auto import tqdm

        return tqdm(**common)
    from tqdm import tqdm

    if hasattr(stream, "isatty") and stream.isatty():
        return tqdm(file=stream, dynamic_ncols=True, mininterval=0.1, **common)
    return tqdm(file=_Lines(stream), ncols=80, ascii=True, mininterval=PIPE_EVERY_S, maxinterval=PIPE_EVERY_S * 4,
                **common)


def progress_bar(stream=None, *, min_s: float = 0.5, desc: str = "[run]") -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback drawing a bar of steps for runs longer than ``min_s``
    seconds (short runs print nothing).  The clock starts at the first call, i.e. when the
    stepping starts, so FMU builds before it do not distort the time left."""
    state: dict = {"bar": None, "closed": False}

    def update(done: int, total: int) -> None:
        b = state["bar"]
        if state["closed"]:
            return
        if b is None:
            b = state["bar"] = bar(total, desc, unit="step", stream=stream, delay=min_s)
        if total != b.total:
            b.total = total
        b.update(done - b.n)
        if done >= total:
            b.close()
            state["closed"] = True

    return update


__all__ = ["PIPE_EVERY_S", "bar", "in_notebook", "progress_bar"]
