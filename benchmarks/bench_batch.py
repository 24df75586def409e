"""Batch execution: speed-up of 2 workers against 1, the batch machinery's overhead per run
against the runs themselves, and FMU instance reuse (FMI reset) against loading every FMU again.

The batch: ``pid_step`` (eight FMUs, 1 ms Gauss-Seidel with linear inputs) over a 4 x 4 grid of
the three PIDs' Kp and Kd, 16 runs, on local worker processes, each run writing its trace and
sidecar.  Each figure is the best of ``--repeat`` measurements into fresh directories, after one
warm-up batch (the FMUs are in the cache); the 1- and 2-worker batches and the plain loop take
turns, so that a change of the machine's load hits them alike.

- the runs' own work ("plain"): the same 16 scenes run one after another in this process by the
  code a plain ``rpr-cosim run`` uses (:func:`cosim.run.run`: initialisation, stepping, streaming
  the trace and sidecar), with the FMUs loaded once (timed) and reset between runs as a batch
  worker does;
  once as a batch worker runs them (the trace formatted in the stepping thread: one core) and
  once as ``rpr-cosim run`` does (formatted on a second thread: 1.3 cores).
- speed-up: wall time of the whole batch (:func:`cosim.batch.run_batch`: checking the batch
  file and the scenes, looking up the FMUs, starting the workers, the runs, metrics and rows) on
  1 worker over 2 workers (target >= 1.8x on 2 cores; a worker is one core); the peer: the same
  runs in 1 and 2 independent processes forked from this one, no batch machinery; and 2
  workers against the fastest one-run-at-a-time execution (the plain loop with its writer
  thread, which already uses part of the second core).
- overhead per run: (whole batch on 1 worker - plain one-core runs) / 16, also as % of the
  plain runs (targets: under 5 %, under 50 ms per run for short scenes; also at stop_time 0.5
  s), and the same in CPU time (this process and its workers), which the machine's load
  disturbs less than wall time.
- per-run machinery measured inside one batch (immune to the load changing between batches):
  the worker's time between runs plus its own share of each run, against the run; what is left
  of the whole batch's overhead is its fixed cost (checking the first scene, FMU look-up,
  starting the worker and loading its FMUs, the last row).
- whole cost against stepping (issue 32 item 11): the 16 scenes at stop_time ``--cost-stop``
  (1 s: 1,001 rows of 25 columns on pid_step's 1 ms output grid; 5 s: 5,001) run here as a
  batch worker runs them (one core, the trace written in the stepping thread, the FMUs loaded
  once and reset), with ``.npy``
  traces (the batch default) and with CSV traces, taking turns.  Each run's trace writer is
  timed (:class:`Timed`, wall clock: start, rows, finish with sidecar and placing); the
  stepping is the loop's ``wall_s`` of the same runs with no file (rows in memory), in the
  same pass; ratio (stepping + files) / stepping, the issue's measure (target 1.3x), median
  over ``--repeat`` passes of the 16 runs.
- reuse: initialisation time per run (``init_s``: instantiate or reset, start values,
  initialisation) with instances kept and reset against loading the FMUs for every run.

    python3 benchmarks/bench_batch.py [--repeat 3] [--stop 5.0] [--cost-stop 1.0] [--cost-only]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cosim.batch import load_batch, plan, run_batch  # noqa: E402
from cosim.batch.executors import LocalExecutor  # noqa: E402

BATCH = """\
name: bench
scene: {scene}
set: {{stop_time: {stop}}}
grid:
  Kp: {{path: "components.pid*.params.Kp", values: [20, 30, 45, 60]}}
  Kd: {{path: "components.pid*.params.Kd", values: [10, 15, 20, 30]}}
metrics:
  mech.platform.phi: {{target: 0.2, measure: [overshoot, end_error]}}
"""


def batch_file(tmp: Path, stop: float) -> Path:
    p = tmp / f"bench_{stop:g}.yaml"
    p.write_text(BATCH.format(scene=ROOT / "scenarios" / "pid_step.yaml", stop=stop))
    return p


def one(batch, tmp: Path, workers: int, reuse: bool = True, trace_format: str = "npy") -> dict:
    """A batch on ``workers`` local processes; with 1 worker also the time its worker spends
    between runs (``gaps``: from one run's start to the next's, minus the first run's own
    ``execute`` time, by the worker's clock)."""
    out = Path(tempfile.mkdtemp(dir=tmp))
    starts: list[tuple[float, str]] = []
    c0 = cpu()
    res = run_batch(batch, out=out, executor=LocalExecutor(workers), reuse=reuse, trace_format=trace_format,
                    on_start=lambda task, pid: starts.append((task.started_at, task.run_id)))
    c1 = cpu()
    assert res.ran == len(res.rows) and res.failed == 0, res.rows
    rows = res.rows
    wall_of = {r["run_id"]: r["wall_s"] for r in rows}
    gaps = [t1 - t0 - wall_of[rid] for (t0, rid), (t1, _) in zip(starts, starts[1:])] if workers == 1 else []
    run_s = sum(r["run_s"] for r in rows)
    per = {"whole": sum(r["wall_s"] for r in rows) / len(rows), "run_s": run_s / len(rows),
           "loop": sum(r["loop_s"] for r in rows) / len(rows)}
    return {"wall": res.wall_s, "execution": res.wall_s - res.prepare_s, "prepare": res.prepare_s,
            "worker": sum(r["wall_s"] for r in rows) - run_s, "run": run_s,
            "init": sum(r["init_s"] for r in rows) / len(rows), "n": len(rows), "cpu": c1 - c0, "gaps": gaps,
            "per": per}


def cpu() -> float:
    """CPU time [s] of this process and its finished children (the workers, once joined)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class Plain:
    """The batch's scenes run one after another here by :func:`cosim.run.run`: the FMUs loaded
    once per call (as a worker loads them once per batch) and their instances kept and reset."""

    def __init__(self, batch):
        from cosim.run.execute import build_components

        self.scenes = [p.scene for p in plan(batch)[0]]
        self.paths = build_components(self.scenes[0])

    def slaves(self) -> list:
        from cosim.slaves.fmu_slave import FmuSlave

        out = [FmuSlave(name, self.paths[name]) for name in self.scenes[0].components]
        for s in out:
            s.reuse = True
        return out

    def __call__(self, tmp: Path, writer_thread: bool = False, trace_format: str | None = "csv") -> dict:
        from cosim.trace import traces as trace

        trace.WRITER_THREAD = writer_thread
        try:
            return self._loop(tmp, trace_format)
        finally:
            trace.WRITER_THREAD = True

    def _loop(self, tmp: Path, trace_format: str | None = "csv") -> dict:
        """The runs writing their trace files in ``trace_format`` (``rpr-cosim run``'s default:
        CSV), or with None no file (the rows kept in memory: the stepping alone)."""
        from cosim.run.execute import run

        out = Path(tempfile.mkdtemp(dir=tmp))
        c0, t0, m0 = cpu(), time.perf_counter(), time.perf_counter()
        loop = trace = 0.0
        slaves = self.slaves()
        for i, scene in enumerate(self.scenes):
            t1 = time.perf_counter()
            res = run(scene, out_dir=out / str(i) if trace_format else None, slaves=slaves,
                      trace_format=trace_format or "csv")
            assert res.ok, res.reason
            loop += res.stats["wall_s"]
            trace += time.perf_counter() - t1 - res.stats["wall_s"] - res.stats["init_s"]
        n = len(self.scenes)
        return {"wall": time.perf_counter() - t0, "n": n, "loop": loop, "trace": trace, "cpu": cpu() - c0,
                "main_cpu": time.perf_counter() - m0}


def independent(plain: Plain, tmp: Path, procs: int) -> dict:
    """The peer of the speed-up: the plain runs split over ``procs`` independent processes forked
    from this one (no batch machinery, nothing shared), started together; their wall time.  Two
    such processes against one is what this machine and these runs allow 2 workers to gain."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    go, done = ctx.Barrier(procs + 1), ctx.Queue()

    def child(k: int) -> None:
        from cosim.trace import traces as trace
        from cosim.run.execute import run

        trace.WRITER_THREAD = False  # one core each, as a batch worker
        out = Path(tempfile.mkdtemp(dir=tmp))
        go.wait()
        slaves = plain.slaves()
        for i, scene in enumerate(plain.scenes[k::procs]):
            assert run(scene, out_dir=out / str(i), slaves=slaves).ok
        done.put(k)

    kids = [ctx.Process(target=child, args=(k,)) for k in range(procs)]
    for p in kids:
        p.start()
    go.wait()
    t0 = time.perf_counter()
    for _ in kids:
        done.get()
    wall = time.perf_counter() - t0
    for p in kids:
        p.join()
    return {"wall": wall}


def best(fns: dict, repeat: int, rounds: list | None = None) -> dict:
    """The best (least wall) of ``repeat`` results of each function, the functions taking turns;
    each round's results are appended to ``rounds`` (for ratios within a round)."""
    out: dict = {}
    for _ in range(repeat):
        this = {}
        for name, fn in fns.items():
            m = this[name] = fn()
            if name not in out or m["wall"] < out[name]["wall"]:
                out[name] = m
        if rounds is not None:
            rounds.append(this)
    return out


def median_ratio(rounds: list, a: str, b: str) -> float:
    """The median over rounds of wall(a) / wall(b) measured back to back (a slow spell of the
    machine hits both sides of one ratio)."""
    import statistics

    return statistics.median(r[a]["wall"] / r[b]["wall"] for r in rounds)


def overhead(b1: dict, plain: dict) -> str:
    n = plain["n"]
    per = (b1["wall"] - plain["wall"]) / n
    exec_per = (b1["execution"] - plain["wall"]) / n
    return (f"{1e3 * per:.1f} ms per run = {100 * per * n / plain['wall']:.1f} % of the runs' own "
            f"{1e3 * plain['wall'] / n:.1f} ms (stepping {1e3 * plain['loop'] / n:.1f} ms, trace files "
            f"{1e3 * plain['trace'] / n:.1f} ms); of which resolving and checking the scenes, FMU look-up "
            f"{1e3 * b1['prepare'] / n:.1f} ms, execution {1e3 * exec_per:.1f} ms "
            f"({100 * exec_per * n / plain['wall']:.1f} %; the worker's own share {1e3 * b1['worker'] / n:.1f} ms: "
            f"instances, metrics); CPU time per run {1e3 * b1['cpu'] / n:.1f} ms against "
            f"{1e3 * plain['cpu'] / n:.1f} ms (+{100 * (b1['cpu'] / plain['cpu'] - 1):.1f} %; less sensitive to the "
            f"machine's load than wall time)")


def within(b: dict) -> str:
    """The machinery's time per run measured inside one batch (immune to load changes between
    batches): the worker's time between runs (median gap) plus its own share of each run
    (instances, metrics, sending the row: ``wall_s - run_s``), against the run itself."""
    import statistics

    gap = statistics.median(b["gaps"])
    share = b["worker"] / b["n"]
    run = b["run"] / b["n"]
    return (f"{1e3 * (gap + share):.2f} ms = {100 * (gap + share) / run:.1f} % of a run's {1e3 * run:.1f} ms "
            f"(between runs {1e3 * gap:.2f} ms, the worker's share {1e3 * share:.2f} ms); the rest of the batch's "
            f"overhead is its fixed cost")


def fixed_cost(b: dict, plain: dict) -> float:
    """The whole batch's overhead over the plain loop less its per-run machinery (:func:`within`)."""
    import statistics

    return (b["wall"] - plain["wall"]) - b["n"] * (statistics.median(b["gaps"]) + b["worker"] / b["n"])


class Timed:
    """A run's trace writer, timed by the wall clock: the time spent inside it (``files``: start,
    rows, text, finish with the sidecar and placing)."""

    def __init__(self, inner) -> None:
        self.inner, self.files, self.rows, self.stepping, self._mark = inner, 0.0, 0.0, 0.0, None

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def _timed(self, fn, *args):
        t0 = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.files += time.perf_counter() - t0

    def start(self, columns, meta) -> None:
        self._timed(self.inner.start, columns, meta)
        self._mark, self._inside = time.perf_counter(), self.files

    def record(self, rows) -> None:
        before = self.files
        self._timed(self.inner.record, rows)
        self.rows += self.files - before

    def record_text(self, t, column, value) -> None:
        self._timed(self.inner.record_text, t, column, value)

    def finish(self, status, reason, stats) -> None:
        if self._mark is not None:
            self.stepping = time.perf_counter() - self._mark - (self.files - self._inside)
        self._timed(self.inner.finish, status, reason, stats)


def cost(plain: Plain, tmp: Path, repeat: int, stop: float) -> None:
    """Whole cost of a batch's run against its stepping, ``.npy`` and CSV traces (module docstring)."""
    import statistics

    from cosim.run import execute

    made: list[Timed] = []
    original = execute.trace_writer

    def timed_writer(*args, **kwargs):
        made.append(Timed(original(*args, **kwargs)))
        return made[-1]

    execute.trace_writer = timed_writer
    try:
        ratios: dict[str, list[float]] = {"npy": [], "csv": []}
        parts: dict[str, list[tuple[float, float]]] = {"npy": [], "csv": []}
        for _ in range(repeat):
            bare = plain(tmp, trace_format=None)
            step = bare["loop"] / bare["n"]
            for fmt in ratios:
                made.clear()
                plain(tmp, trace_format=fmt)
                files = sum(w.files for w in made) / len(made)
                ratios[fmt].append((step + files) / step)
                parts[fmt].append((step, files, sum(w.rows for w in made) / len(made)))
    finally:
        execute.trace_writer = original
    for fmt, values in ratios.items():
        step, files, rows = (statistics.median(p[k] for p in parts[fmt]) for k in (0, 1, 2))
        print(f"whole cost / stepping of a batch run, {stop:g} s pid_step runs, one core, {fmt} traces: "
              f"{statistics.median(values):.2f}x (median of {len(values)} passes of 16 runs; {min(values):.2f}-"
              f"{max(values):.2f}x; target 1.3x): {1e3 * step:.1f} ms stepping + {1e3 * files:.1f} ms writing the "
              f"trace and sidecar per run (of which the rows {1e3 * rows:.1f} ms; the rest: opening, the sidecar with "
              f"the whole scene, placing)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stop", type=float, default=5.0, help="stop_time of the runs [s]")
    ap.add_argument("--cost-stop", type=float, default=1.0, help="stop_time of the whole-cost runs [s]")
    ap.add_argument("--cost-only", action="store_true", help="only the whole cost against stepping")
    args = ap.parse_args()
    print("overhead per run = (wall time of the whole batch on 1 worker - the same runs one after another "
          "by cosim.run.run in one process, instances kept) / runs")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        batch = load_batch(batch_file(tmp, args.stop))
        short = load_batch(batch_file(tmp, 0.5))
        t0 = time.perf_counter()
        one(batch, tmp, 2)  # warm-up: FMUs
        print(f"warm-up batch: {time.perf_counter() - t0:.2f} s")
        cost(Plain(load_batch(batch_file(tmp, args.cost_stop))), tmp, args.repeat, args.cost_stop)
        if args.cost_only:
            return
        plain, plain_short = Plain(batch), Plain(short)
        m = best({"1": lambda: one(batch, tmp, 1), "2": lambda: one(batch, tmp, 2),
                  "plain": lambda: plain(tmp), "threaded": lambda: plain(tmp, writer_thread=True),
                  "peer1": lambda: independent(plain, tmp, 1), "peer2": lambda: independent(plain, tmp, 2)},
                 args.repeat, rounds := [])
        m1, m2, p, pt = m["1"], m["2"], m["plain"], m["threaded"]
        ceiling = m["peer1"]["wall"] / m["peer2"]["wall"]
        print(f"CPU time of the whole batch (this process and the workers): 1 worker {m1['cpu']:.2f} s, 2 workers "
              f"{m2['cpu']:.2f} s; the runs one after another {p['cpu']:.2f} s (one core), {pt['cpu']:.2f} s "
              f"(trace on a second thread)")
        print(f"16 runs of pid_step ({args.stop:g} s each): whole batch 1 worker {m1['wall']:.2f} s, 2 workers "
              f"{m2['wall']:.2f} s: speed-up {m1['wall'] / m2['wall']:.2f}x (target 1.8x); execution alone "
              f"{m1['execution']:.2f} s vs {m2['execution']:.2f} s: {m1['execution'] / m2['execution']:.2f}x")
        print(f"median over the {len(rounds)} rounds of the ratio measured back to back: batch 1 worker / 2 workers "
              f"{median_ratio(rounds, '1', '2'):.2f}x (target 1.8x), peer 1 / 2 processes "
              f"{median_ratio(rounds, 'peer1', 'peer2'):.2f}x, batch 1 worker / plain one-core loop "
              f"{median_ratio(rounds, '1', 'plain'):.3f}")
        print(f"peer: the same runs in 1 vs 2 independent one-core processes (no batch machinery): "
              f"{m['peer1']['wall']:.2f} s vs {m['peer2']['wall']:.2f} s = {ceiling:.2f}x, what this machine "
              f"allows; the batch reaches {100 * (m1['wall'] / m2['wall']) / ceiling:.0f} % of it")
        main_ms, other_ms = 1e3 * pt["main_cpu"] / pt["n"], 1e3 * (pt["cpu"] - pt["main_cpu"]) / pt["n"]
        print(f"against the fastest one-at-a-time execution (rpr-cosim run's loop, the trace formatted on a second "
              f"thread: {main_ms:.1f} ms stepping + {other_ms:.1f} ms formatting per run, {pt['wall']:.2f} s): 2 "
              f"workers {pt['wall'] / m2['wall']:.2f}x; such a loop keeps {(main_ms + other_ms) / main_ms:.2f} "
              f"cores busy, so 2 cores can make it at most {2 * main_ms / (main_ms + other_ms):.2f}x faster")
        print(f"overhead, 1 worker, {args.stop:g} s runs: {overhead(m1, p)} (targets 5 %, 50 ms)")
        print(f"per-run machinery inside one batch, 1 worker, {args.stop:g} s runs: {within(m1)} (target 5 %); "
              f"fixed cost of the batch {1e3 * fixed_cost(m1, p):.0f} ms")
        ms = best({"1": lambda: one(short, tmp, 1), "plain": lambda: plain_short(tmp)}, args.repeat)
        print(f"overhead, 1 worker, 0.5 s runs: {overhead(ms['1'], ms['plain'])} (target 50 ms)")
        print(f"per-run machinery inside one batch, 1 worker, 0.5 s runs: {within(ms['1'])}")
        mr = best({"reuse": lambda: one(batch, tmp, 1), "reload": lambda: one(batch, tmp, 1, reuse=False)},
                  args.repeat)
        a, b = mr["reuse"], mr["reload"]
        print(f"initialisation per run: instances kept and reset {1e3 * a['init']:.1f} ms, FMUs loaded for every "
              f"run {1e3 * b['init']:.1f} ms ({b['init'] / a['init']:.0f}x); the 16 runs' batch "
              f"{a['wall']:.2f} s vs {b['wall']:.2f} s ({b['wall'] / a['wall']:.2f}x)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
