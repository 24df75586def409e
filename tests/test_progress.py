"""Progress by tqdm: redrawn in place on a terminal, whole lines without control characters in a
pipe (logs), nothing for a run shorter than the delay; the batch's bar counts runs."""
from __future__ import annotations

import io
import time

from cosim.batch.overview import Progress
from cosim.run.progress import progress_bar


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_run_bar_in_a_pipe_is_whole_lines_without_control_characters():
    out = io.StringIO()
    update = progress_bar(out, min_s=0.0)
    for done in range(0, 1001, 50):
        update(done, 1000)
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert lines and lines[-1].startswith("[run]: 100%") and "1000/1000" in lines[-1]


def test_a_run_bar_on_a_terminal_is_redrawn_in_place():
    out = Tty()
    update = progress_bar(out, min_s=0.0)
    for done in range(0, 1001, 100):
        update(done, 1000)
        time.sleep(0.11)  # past tqdm's refresh interval on a terminal
    text = out.getvalue()
    assert text.count("\r") >= 5 and "1000/1000" in text


def test_a_short_run_prints_nothing():
    out = io.StringIO()
    update = progress_bar(out, min_s=5.0)
    for done in range(0, 101, 10):
        update(done, 100)
    assert out.getvalue() == ""


def test_the_batch_bar_counts_runs_and_tells_the_skipped_ones():
    out = io.StringIO()
    p = Progress(out)
    p.begin(5, 0, 0)
    p.skipped_run(True)
    p.skipped_run(False, duplicate=True)  # a point resolving to another run: not counted
    p.show()
    for i in range(3):
        p.started(f"r{i}")
        p.finished(f"r{i}", ok=i != 1)
    p.end()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    assert text.splitlines()[0] == "[batch] 1 of 4 runs already in the table"
    last = text.splitlines()[-1]
    assert "4/4" in last and "1 failed" in last and "0 running" in last
