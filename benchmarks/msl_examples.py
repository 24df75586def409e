"""Every example of the Examples packages of Modelica.Mechanics.Translational,
Modelica.Mechanics.Rotational and Modelica.Blocks (MSL 4.1.0) as a scene component: passing, or
failing with the reason (rumoca's refusal, ours, or a run that does not end ok).

The list is fixed by the library itself (each Examples package's ``package.order``, or the
``model`` classes declared in it), so a refusal counts as a failure, not as out of scope.  For
each example the script writes a one-component scene (``modelica: <example>``, the example's
``experiment`` stop time and interval, or 1 s and 500 steps), then

1. *check*: compiles the class with rumoca (a failure there is rumoca's, with its message), then
   loads the scene (our translation: a failure there is ours, with the construct);
2. *run* (``--run``): builds the FMU and runs it with its error estimate over the recorded
   states (passing is within 1e-3 of range by it); with reference results (``--results``),
   compares the comparison signals (worst error relative to range; passing is within 1e-3).

Each example runs in a forked child with a time limit (``--timeout``, 600 s: a longer one is a
failure "timeout"), so one hang does not stop the survey.  It prints a Markdown table (``--out
FILE`` writes it too) and the timings.  Usage: ``python3 benchmarks/msl_examples.py [--msl DIR]
[--results DIR] [--run] [--only SUBSTRING] [--timeout S]``
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import re
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.run.execute import run  # noqa: E402
from cosim.scenario import SceneError, load  # noqa: E402
from cosim.scenario.modelica_sources import _NOISE, class_file, modelica_class  # noqa: E402
from models.modelica import ModelicaError  # noqa: E402

THIRD = ROOT.parent / "shared" / "third_party"
PACKAGES = ("Modelica.Mechanics.Translational.Examples", "Modelica.Mechanics.Rotational.Examples",
            "Modelica.Blocks.Examples")
TOLERANCE = 1e-3
#: Integrator substeps where one per output interval is not enough (as tests/test_modelica_msl.py:
#: PID_Controller's stiff spring-damper).
SUBSTEPS = {"Modelica.Blocks.Examples.PID_Controller": 4}
_MODEL = re.compile(r"^\s*(?:encapsulated\s+)?(partial\s+)?(model|package|block|record|function|connector|type|class)"
                    r"\s+([A-Za-z_]\w*)", re.M)


def examples(msl: Path) -> list[str]:
    """The examples (non-partial models) of :data:`PACKAGES` and of their example sub-packages
    (``Blocks.Examples.Noise``; not the ``Utilities`` helpers), in the library's order."""
    out = []
    for pkg in PACKAGES:
        main = class_file(pkg, [msl])
        folder = main.parent if main.name == "package.mo" and main.parent.name == pkg.split(".")[-1] else None
        if folder is not None:  # a directory package: package.order, each entry's own file
            for name in (folder / "package.order").read_text().split():
                f = folder / f"{name}.mo"
                if f.is_file() and _kind(f.read_text(), name) == "model":
                    out.append(f"{pkg}.{name}")
        else:  # a package inside a file (Blocks.Examples in Blocks/package.mo): its member models
            text = _NOISE.sub(" ", main.read_text())
            start = re.search(rf"\bpackage\s+{pkg.split('.')[-1]}\b", text).start()
            end = re.search(rf"\bend\s+{pkg.split('.')[-1]}\s*;", text).end()
            body, stack = text[start:end], []  # the enclosing classes: (kind, name)
            for m in re.finditer(r"\b(?:(end)\s+([A-Za-z_]\w*)\s*;|(partial\s+)?(model|package|block|record|function|"
                                 r"connector|type|class)\s+([A-Za-z_]\w*)(\s*=)?)", body):
                if m.group(1):
                    if m.group(2) not in ("if", "for", "when", "while") and stack:
                        stack.pop()
                    continue
                inside = [n for _, n in stack[1:]]  # the sub-packages of Examples (Noise), not helpers
                if (m.group(4) == "model" and not m.group(3) and all(k == "package" for k, _ in stack)
                        and not any(n.endswith("Utilities") for n in inside)):
                    out.append(".".join([pkg, *inside, m.group(5)]))
                if m.group(6) is None:
                    stack.append((m.group(4), m.group(5)))
    return out


def _kind(text: str, name: str) -> str:
    for m in _MODEL.finditer(text):
        if m.group(3) == name:
            return "partial" if m.group(1) else m.group(2)
    return "?"


def experiment(msl: Path, example: str) -> tuple[float, float]:
    """The example's stop time and output interval [s] from its ``experiment`` annotation."""
    text = class_file(example, [msl]).read_text()
    name = example.split(".")[-1]
    at = re.search(rf"\bmodel\s+{name}\b", text)
    end = re.search(rf"\bend\s+{name}\s*;", text[at.start():]) if at else None
    body = text[at.start():at.start() + end.end()] if at and end else text
    exp = re.search(r"experiment\s*\(([^)]*)\)", body)
    fields = dict(re.findall(r"(\w+)\s*=\s*([-+0-9.eE]+)", exp.group(1))) if exp else {}
    stop = float(fields.get("StopTime", 1.0))
    interval = float(fields.get("Interval", stop / 500))
    return stop, interval


def reason(exc: Exception) -> str:
    line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    line = re.sub(r"^.*?component 'c': ", "", line)
    return line.replace("|", "\\|")[:220]


def one(msl: Path, results: Path | None, example: str, folder: Path, do_run: bool) -> tuple[str, str, str, float]:
    """``(verdict, whose, reason or figure, seconds)`` of one example."""
    stop, interval = experiment(msl, example)
    ref_dir = results / Path(*example.split(".")) if results else None
    signals = []
    if ref_dir is not None and (ref_dir / "comparisonSignals.txt").is_file():
        signals = [s for s in (ref_dir / "comparisonSignals.txt").read_text().split() if s != "time"]
        creation = (ref_dir / "creation.txt").read_text()
        stop = float(creation.split("StopTime=")[1].split()[0])
        interval = float(creation.split("Interval=")[1].split()[0])
    scene = folder / "scene.yaml"
    options = f", options: {{substeps: {SUBSTEPS[example]}}}" if example in SUBSTEPS else ""
    scene.write_text(f"stop_time: {stop}\nmodelica_path: [{msl}]\ncomponents:\n  c: {{modelica: {example}{options}}}\n"
                     f"master: {{algorithm: jacobi, step: {interval}}}\n"
                     + (f"outputs: [{', '.join('c.' + s for s in signals)}]\n" if signals else ""))
    t0 = time.perf_counter()
    try:
        modelica_class(example, None, folder, [msl]).compiled()
    except ModelicaError as exc:
        return "fails", "rumoca", reason(exc), time.perf_counter() - t0
    try:
        loaded = load(scene)
    except SceneError as exc:
        return "fails", "ours", reason(exc), time.perf_counter() - t0
    if not signals:  # no reference result: record the states, so the run's error estimate judges it
        states = [v for v in loaded.components["c"].description.variables if v.startswith("state.") and v != "state.time"]
        if states:
            scene.write_text(scene.read_text() + f"outputs: [{', '.join(json.dumps('c.' + v) for v in states)}]\n")
    if not do_run:
        return "translates", "", "", time.perf_counter() - t0
    try:
        res = run(scene, [], out_dir=folder / "out")
    except Exception as exc:  # noqa: BLE001 - a table row, not a crash of the survey
        return "fails", "ours", f"run: {reason(exc)}", time.perf_counter() - t0
    if not res.ok:
        return "fails", "ours", f"run: {res.reason}"[:220].replace("|", "\\|"), time.perf_counter() - t0
    if not signals:
        est = (res.stats.get("estimate") or {}).get("worst")
        if est is not None and est > TOLERANCE:
            return "fails", "ours", f"runs to {stop:g} s, estimated {est:.1e} of range, beyond {TOLERANCE:g} " \
                                    f"(no reference result here)", time.perf_counter() - t0
        said = f", estimated {est:.1e} of range" if est is not None else ", no error estimate (no states)"
        return "passes", "", f"runs to {stop:g} s{said} (no reference result here)", time.perf_counter() - t0
    import pandas as pd

    ref = pd.read_csv(ref_dir / f"{example.split('.')[-1]}.csv")
    worst = max(float(np.abs(res.trace[f"c.{s}"] - np.interp(res.trace["time"], ref["time"], ref[s])).max()
                      / max(np.ptp(ref[s]), 1e-300)) for s in signals)
    verdict = "passes" if worst < TOLERANCE else "fails"
    return verdict, "" if worst < TOLERANCE else "ours", f"against the MA reference result: worst {worst:.1e} of " \
                                                         f"range", time.perf_counter() - t0


def limited(timeout: float, *args) -> tuple[str, str, str, float]:
    """:func:`one` in a forked child, killed after ``timeout`` seconds (a failure "timeout")."""
    t0 = time.perf_counter()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read)
        try:
            out = one(*args)
        except BaseException as exc:  # noqa: BLE001 - a row, whatever happened
            out = ("fails", "ours", f"crashed: {reason(exc)}", time.perf_counter() - t0)
        with os.fdopen(write, "wb") as fh:
            pickle.dump(out, fh)
        os._exit(0)
    os.close(write)
    signal.signal(signal.SIGALRM, lambda *_: os.kill(pid, signal.SIGKILL))
    signal.alarm(max(1, int(timeout)))
    with os.fdopen(read, "rb") as fh:
        data = fh.read()
    signal.alarm(0)
    os.waitpid(pid, 0)
    if not data:
        return "fails", "", f"timeout: no result within {timeout:g} s", time.perf_counter() - t0
    return pickle.loads(data)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--msl", type=Path, default=THIRD / "modelica-standard-library")
    ap.add_argument("--results", type=Path, default=THIRD / "msl-reference-results")
    ap.add_argument("--run", action="store_true", help="also build and run each example that translates")
    ap.add_argument("--only", default="", help="only the examples whose name contains this")
    ap.add_argument("--out", type=Path, help="also write the Markdown table here")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per example (default 600)")
    args = ap.parse_args(argv)
    if not (args.msl / "Modelica" / "package.mo").is_file():
        print(f"no Modelica Standard Library at {args.msl} (give --msl DIR)", file=sys.stderr)
        return 2
    rows = ["| example | result | whose | reason or figure | time [s] |", "|---|---|---|---|---|"]
    todo = [e for e in examples(args.msl) if args.only in e]
    with tempfile.TemporaryDirectory() as tmp:
        for k, example in enumerate(todo):
            folder = Path(tmp) / str(k)
            folder.mkdir()
            verdict, whose, why, secs = limited(args.timeout, args.msl, args.results if args.results.is_dir()
                                                else None, example, folder, args.run)
            short = example.replace("Modelica.Mechanics.", "").replace("Modelica.", "")
            rows.append(f"| `{short}` | {verdict} | {whose} | {why} | {secs:.1f} |")
            print(rows[-1], flush=True)
    counts = {v: sum(f"| {v} |" in r for r in rows[2:]) for v in ("passes", "translates", "fails")}
    whose = {w: sum(f"| fails | {w} |" in r for r in rows[2:]) for w in ("rumoca", "ours")}
    summary = ", ".join(f"{n} {v}" for v, n in counts.items() if n) + \
        (f" ({whose['rumoca']} refused by rumoca, {whose['ours']} by us or failing in our run)" if counts["fails"] else "")
    print(f"{len(todo)} examples: {summary}")
    if args.out:
        args.out.write_text("\n".join(rows) + f"\n\n{len(todo)} examples: {summary}.\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
