"""The keys a scene file may use, and the values of its enumerated settings."""
from __future__ import annotations


TOP_KEYS = ("name", "description", "include", "start_time", "stop_time", "components", "connections", "master",
            "outputs", "fidelity_tolerance", "fidelity_signals", "guards", "blocks")
COMPONENT_KEYS = ("model", "fidelity", "options", "params", "start", "fmu", "fmi", "description", "hardware",
                  "rollback", "rate", "modelica", "guard_data")
MASTER_KEYS = ("algorithm", "step", "order", "engine", "output_interval", "inputs", "realtime", "options", "tolerance")
#: The accuracy a scene gets when it names no master algorithm (cosim.run.choose).
DEFAULT_TOLERANCE = 1e-3
#: How a slave's inputs vary over a communication step (see :mod:`cosim.master`).
INPUT_MODES = ("hold", "linear")
ENGINES = ("auto", "compiled", "python")
FMI_VERSIONS = ("2.0", "3.0")
