"""The driver loop's contract points for events (docs/explanation/events.md), with a stepper
that reports one: a block that ends early at an event time gives the left-limit row, the event
iteration runs at that instant, the right-limit row follows at the same time, and observers hear
of the event; the rows away from it are those of a run without it (the exact Jacobi map of a
linear pair)."""
from __future__ import annotations

import numpy as np

from cosim.master import CoupledSystem, Link, algorithm
from cosim.master.engine import fixed_stepper
from cosim.master.lifecycle import initialize
from cosim.master.stepper import FixedStepper, StepResult, drive, record_start
from cosim.slaves.linear import LinearSlave
from cosim.trace.observer import Observer
from cosim.trace.traces import MemoryTrace


def pair() -> CoupledSystem:
    a = LinearSlave("a", [[-1.0]], [[1.0]], [[1.0]], x0=[1.0])
    b = LinearSlave("b", [[-3.0]], [[1.0]], [[0.8]], [[0.5]], x0=[-0.4])
    return CoupledSystem([a, b], [Link(0, "y[1]", 1, "u[1]"), Link(1, "y[1]", 0, "u[1]")], [(0, "y[1]"), (1, "y[1]")])


class EventAt(FixedStepper):
    """Jacobi on its compiled loop with an event of component a at step ``k_event``: the block ends
    there, and the event iteration negates a's output (an update ``y+ = -y-``)."""

    def __init__(self, base: FixedStepper, k_event: int):
        super().__init__(base.alg, base.runner, base.n_steps, base.record_every, base.engine)
        self.k_event, self.fired, self.iterated = k_event, False, []

    def block(self, rec, max_steps):
        if not self.fired:
            max_steps = min(max_steps, self.k_event - self.alg.k)
        rows = super().block(rec, max_steps)
        if not self.fired and self.alg.k == self.k_event:
            self.fired = True
            self.event = StepResult(self.t_ns, event=True, component=0, kind="x[1] < 0")
        return rows

    def event_iteration(self, event):
        self.iterated.append(event.t_ns)
        k = self.system.index[(0, "y[1]")]
        self.system.v[k] = -self.system.v[k]


class Events(Observer):
    def __init__(self):
        self.events = []

    def start(self, columns, meta):
        pass

    def record(self, rows):
        pass

    def finish(self, status, reason, stats):
        pass

    def record_event(self, t, component, kind):
        self.events.append((t, component, kind))


def run(k_event: int | None, n_steps: int = 10):
    system = pair()
    initialize(system, [{}, {}], stop_time=n_steps * 0.1)
    stepper = fixed_stepper(system, cls=algorithm("jacobi"), step_ns=100_000_000, n_steps=n_steps, record_every=1,
                            engine="compiled")
    if k_event is not None:
        stepper = EventAt(stepper, k_event)
    mem, events = MemoryTrace(), Events()
    columns = ["time"] + system.record_names
    for obs in (mem, events):
        obs.start(columns, {})
    record_start(stepper, system, [mem, events], None, len(columns))
    drive(stepper, system, [mem, events], n_columns=len(columns))
    mem.finish(stepper.status, stepper.message, {})
    return mem.trace, events.events, stepper


def test_an_event_gives_two_rows_at_its_time_and_the_hooks_run_there():
    plain, _, _ = run(None)
    trace, events, stepper = run(3)
    t = trace.time
    assert len(t) == len(plain.time) + 1 and np.all(np.diff(t) >= 0)
    same = np.flatnonzero(np.diff(t) == 0)
    assert list(same) == [3] and t[3] == t[4] == plain.time[3]  # one pair, at the event
    assert np.array_equal(trace.data[:4], plain.data[:4])  # up to the left limit: the run without the event
    assert trace.data[4, 1] == -trace.data[3, 1] and trace.data[4, 2] == trace.data[3, 2]  # the right limit
    assert stepper.iterated == [300_000_000]
    assert events == [(0.3, "a", "x[1] < 0")]
    assert stepper.status == "running" and stepper.alg.k == 10


def test_without_an_event_the_hooks_do_nothing():
    trace, events, stepper = run(None)
    assert events == [] and stepper.event is None and stepper.next_output_ns(0) is None
    assert np.all(np.diff(trace.time) > 0) and len(trace.time) == 11


def test_an_observer_that_does_not_override_step_does_not_watch_steps():
    assert not Events.watches_steps() and not MemoryTrace.watches_steps()

    class Watching(Events):
        def step(self, info):
            return None

    assert Watching.watches_steps()
