"""Traces: the outputs of a run at its communication points, recorded by observers
(:mod:`.observer`: the contract; :mod:`.traces`: the in-memory and streamed CSV traces, reading
them back) and written fast (:mod:`.text`)."""
from .observer import Observer
from .traces import CsvTrace, MemoryTrace, Trace, TraceWriteError, read_trace

__all__ = ["CsvTrace", "MemoryTrace", "Observer", "Trace", "TraceWriteError", "read_trace"]
