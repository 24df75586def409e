"""The keys a scene file may use, each with what it means, and the values of its enumerated
settings.  The checkers (:mod:`cosim.scenario.validate`, ``check_*.py``) accept exactly these keys,
and the documentation's scene-format reference is generated from these declarations."""
from __future__ import annotations

#: Top-level keys of a scene file -> what each holds.
TOP = {
    "name": "the scene's name, the stem of every file a run writes (letters, digits, `_`, `-`, `.`; at most 100 "
            "characters; default: the file's stem)",
    "description": "free text",
    "include": "another scene file (or an SSP archive) to start from; this file's keys then override it",
    "start_time": "simulated start time [s] (default 0, or the FMUs' DefaultExperiment)",
    "stop_time": "simulated stop time [s] (default: the FMUs' DefaultExperiment when they agree)",
    "components": "mapping of component name -> component (catalog block, FMU file or hardware), see below",
    "connections": "list of `src.output -> dst.input [* factor + offset] [as TYPE]` signals and "
                   "`a.port <-> b.port` power bonds",
    "master": "the master algorithm and its settings, see below",
    "outputs": "the recorded variables: `component.variable` names or globs (`mech.platform.*`, `motor*.i`; a glob reaches inputs and outputs, and every variable of a Modelica component: `osc.mass1.*`, `osc.*`, where its component part matches the component's name)",
    "fidelity_tolerance": "tolerance of `fidelity: auto` (relative to range, default 1e-3)",
    "fidelity_signals": "globs of the signals `fidelity: auto` compares (default: every recorded signal)",
    "guards": "the physical guards (`stroke`, `rated`, `singularity`, `unstable`: stop | warn | off; "
              "`min_det` [m], `max_abs`), or `off`",
    "blocks": "Python files of your own blocks (each defines `BLOCKS`), relative to the scene; their models are "
              "then used like catalog ones",
    "modelica_path": "Modelica source roots (directories holding libraries such as `Modelica/`), a list or a "
                     "`:`-separated string, relative to the scene; searched before `MODELICAPATH`",
}
#: Keys of one component -> what each holds.
COMPONENT = {
    "model": "a catalog model (`rpr-cosim fmu list`): mechanism, dc_motor, pid, pose_setpoint, ...",
    "fidelity": "the model's fidelity level (e.g. rigid, multibody, kinematic), or `auto` (the cheapest within "
                "`fidelity_tolerance`)",
    "options": "the model's build options (e.g. `config`, `integrator`, `substeps`; a Modelica component's "
               "`causality: {FLANGE: effort_out | flow_out}` states which side of a bond computes the force where "
               "the model allows both)",
    "params": "parameter values by name (units as `rpr-cosim fmu show` lists them; structural parameters of FMI 3.0 "
              "FMUs too)",
    "start": "start values of inputs and of variables with initial = exact or approx",
    "fmu": "path of an FMI 2.0 or 3.0 FMU (co-simulation or model exchange) from any tool, instead of `model`",
    "interface": "which interface of an FMU that has both runs: `co_simulation` (the default where the FMU has it) "
                 "or `model_exchange` (integrated by CVODES inside its slave)",
    "rtol": "a model-exchange FMU's CVODES relative tolerance (default 1e-6, or the FMU's DefaultExperiment "
            "tolerance when tighter; absolute: rtol times each state's nominal)",
    "fmi": "FMI version of a catalog block's FMU: `2.0` (default) or `3.0`",
    "description": "free text",
    "hardware": "the rig's I/O daemon: `{address: HOST:PORT, key: FILE}` (the hardware FMU)",
    "replay": "a recording played back (CSV or Parquet with a `time` column [s]): each column an output "
              "(docs/how-to/calibrate.md)",
    "interpolation": "a replay's interpolation between samples: `linear` (default) or `hold`",
    "units": "a replay's column units, `{COLUMN: UNIT}` (win over the file's metadata)",
    "rollback": "`false`: treat the component as one that cannot save and restore its state",
    "rate": "doSteps per macro step (multirate, a whole number >= 1 dividing the step into whole nanoseconds)",
    "modelica": "a Modelica file of your own (`.mo`), with `model:` naming its class (e.g. `Drive.RackPinion`), or a "
                "class of the Modelica source roots by its full name (e.g. "
                "`Modelica.Mechanics.Translational.Examples.Oscillator`)",
    "guard_data": "what the physical guards know of an external FMU (its mechanism, legs and ratings; written by "
                  "`ssp export` into an rpr-cosim SSP's component annotation)",
    "feedthrough": "an FMU's direct feedthrough, which wins over its XML and the measured one: `none`, `all`, or a "
                   "mapping output -> list of inputs (unlisted outputs have none)",
    "flanges": "power ports of an FMU: `{NAME: {effort: VAR, flow: VAR}}` (one input, one output), bonded with "
               "`a.NAME <-> b.NAME` (see docs/external-fmus.md)",
}
#: Keys of ``master:`` -> what each holds.
MASTER = {
    "algorithm": "the coupling algorithm: jacobi, gauss_seidel, iterative, adaptive, ecco (see the algorithms "
                 "reference); none named: the master chooses one from `tolerance` (docs/accuracy.md)",
    "step": "communication step [s] (for variable-step algorithms, the unit of stop_time only)",
    "order": "Gauss-Seidel stepping order: a list of component names (default: found from the connections)",
    "engine": "auto (default) or compiled: the algorithm's compiled loop (a run needs a C compiler; `python` is gone, "
              "the Python loops are test oracles); compiled also refuses, with the reason, a scene its loop cannot run",
    "output_interval": "recording interval [s], a whole multiple of the step (default: the step); variable-step "
                       "algorithms land a step on every output point",
    "record": "grid (default): a row at every output point (output_interval) plus two per event; steps: a row at "
              "every step a variable-step algorithm accepted instead (irregular times)",
    "inputs": "how inputs vary over a step: hold (zero-order) or linear (interpolated / extrapolated)",
    "realtime": "`true`, or `{max_misses, spin, priority}`: pace the communication points on the wall clock",
    "options": "the algorithm's own options (declared by the algorithm, see the algorithms reference)",
    "estimate": "true (default): the run estimates its own error per signal from a companion run at half the "
                "step or a quarter of the tolerance, and a run it shows wrong is not ok; false: no estimate (a "
                "batch of many runs does half the work)",
    "tolerance": "the worst error of a recorded signal relative to its range, in (0, 0.5); default 1e-3 (no "
                 "algorithm named: the master chooses one to meet it); a run whose own error estimate is over 10x "
                 "it ends inaccurate, a named algorithm's too; `none` with a named algorithm: no verdict",
}
TOP_KEYS = tuple(TOP)
COMPONENT_KEYS = tuple(COMPONENT)
MASTER_KEYS = tuple(MASTER)
#: How a slave's inputs vary over a communication step (see :mod:`cosim.master`).
INPUT_MODES = ("hold", "linear")
#: ``master.engine`` (as :data:`cosim.master.engine.ENGINES`; a test may register its oracle besides them)
ENGINES = ("auto", "compiled")
#: What a run records (``master.record``): the output grid, or every accepted step of a variable-step master.
RECORD_MODES = ("grid", "steps")
#: The accuracy a scene gets when it names no master algorithm (cosim.run.choose).
DEFAULT_TOLERANCE = 1e-3
FMI_VERSIONS = ("2.0", "3.0")
