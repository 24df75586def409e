"""The command line's grammar: every verb's arguments, declared in one place (the options that
several verbs share are declared once in :mod:`cosim.cli.options`).

A verb's handler is named as ``"<module>:<function>"`` of :mod:`cosim.cli` (``"run_verb:_run"``)
and imported only when that verb runs, so that ``rpr-cosim --help`` and the parser load no
numerical package (:func:`cosim.cli.handler`).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .options import (add_actions, add_cache, add_only, add_out, add_report, add_scene, add_sets, add_tol,
                      add_trace_format, add_variants, add_verb)

DEFAULT_MONTE_CARLO = 100_000

CATALOG_SCENE_HELP = "scene file of catalog components, e.g. scenarios/pid_step.yaml"

STUDY_CACHE_HELP = "FMU cache directory"


def _analyze(sub: argparse._SubParsersAction) -> None:
    p = add_verb(
        sub, "analyze", "analyze_verb:run",
        help="workspace, singularity and DSI maps; the thesis's configuration and platform studies",
        description="Constant-orientation workspace, det J and DSI maps (PNG), singularity curves, and the "
                    "thesis's Table 4.5 (four configurations) and Table 4.9 (platform size) as text and CSV.")
    p.add_argument("--config", default="cross_leg", metavar="NAME",
                   help="design(s) to map: config1..config4, classic, cross_leg, a comma-separated list, or 'all' (default cross_leg)")
    p.add_argument("--grid", default=None, metavar="N",
                   help="grid side N >= 2 over [-60, 60) cm (default: the thesis's, 500 or 800 for config3; "
                        "120 for the platform-size study)")
    p.add_argument("--phi", default="0", metavar="RAD", help="platform orientation in rad (default 0)")
    p.add_argument("--study", default="configs", metavar="STUDY",
                   help="configs (Table 4.5), platform-size (Table 4.9, Figs 4.10-4.11), all, or none "
                        "(default configs)")
    p.add_argument("--monte-carlo", default=str(DEFAULT_MONTE_CARLO), metavar="N",
                   help=f"Monte Carlo samples for the workspace area, 0 to skip (default {DEFAULT_MONTE_CARLO})")
    p.add_argument("--seed", default="0", metavar="S", help="random seed of the Monte Carlo estimate (default 0)")
    p.add_argument("--out", default="out/analysis", metavar="DIR", help="output directory (default ./out/analysis)")


def _fmu(sub: argparse._SubParsersAction) -> None:
    verbs = add_actions(sub, "fmu", "fmu_verb", help="build co-simulation FMUs and list the FMU cache",
                        description="Build FMI 2.0/3.0 co-simulation FMUs from the model catalog, list the "
                                    "catalog and the cache, and validate any FMU.")
    b = add_verb(verbs, "build", "fmu_verb:_build", help="build (or fetch from the cache) one FMU",
                 description="Build one catalog model as a co-simulation FMU: CasADi generates its C, gcc "
                             "compiles it, and the result is cached by content (a second build of the same "
                             "block compiles nothing; a damaged cache entry is rebuilt).  Prints the FMU's "
                             "path on stdout.")
    b.add_argument("model", help="catalog model, e.g. mechanism, dc_motor, pid, pose_setpoint; or a user's block: "
                                 "FILE.mo:CLASS or FILE.py:MODEL[/FIDELITY]")
    b.add_argument("--fidelity", help="fidelity level (default: the model's first)")
    add_sets(b, "parameter override or construction option; repeatable", metavar="NAME=VALUE")
    b.add_argument("--fmi", choices=["2", "3"], default="2", help="FMI version (default 2)")
    add_out(b, "also copy the FMU into this directory")
    add_cache(b, "cache directory (default $RPR_COSIM_CACHE or ~/.cache/rpr-cosim/fmus)")
    ls = add_verb(verbs, "list", "fmu_verb:_list", help="show the model catalog and the cached FMUs",
                  description="List the catalog's models with their fidelities, and every FMU in the cache "
                              "with its FMI version, integrator, states and build time.")
    add_cache(ls, "cache directory")
    ck = add_verb(verbs, "check", "fmu_verb:_check", help="validate an FMU's modelDescription.xml (FMPy's checks)",
                  description="Validate any FMU: the archive (a zip whose members stay inside it) and its "
                              "modelDescription.xml against the FMI schema and FMPy's rules.  Prints one "
                              "line per problem; the exit code is their number (at most 100).")
    ck.add_argument("fmu", type=Path, help="the .fmu file")
    ck.add_argument("--behaviour", action="store_true",
                    help="also run the FMU (two instances, state get/set/free, the noSetFMUStatePriorToCurrentPoint "
                         "flag, reset, determinism, directional derivatives, setters, stop time) and print each "
                         "departure from the FMI standard, and the workarounds a run applies")
    sh = add_verb(verbs, "show", "fmu_verb:_show", help="interface, parameters (units, defaults, bounds), states and integrator "
                                             "of a catalog model or an FMU file")
    sh.add_argument("what", nargs="?", help="MODEL[/FIDELITY] (e.g. pid/continuous), FILE.fmu, or a user's block: "
                                            "FILE.mo:CLASS or FILE.py:MODEL[/FIDELITY]")
    sh.add_argument("--markdown", nargs="?", const="-", metavar="FILE",
                    help="write the same as a Markdown page (to FILE, default stdout)")
    sh.add_argument("--readme", nargs="?", const="README.md", type=Path, metavar="README",
                    help="rewrite the generated model section (between its BEGIN/END markers) of a Markdown file "
                         "from the catalog; the documentation site's model catalog is generated at build time")


def _run(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "run", "run_verb:_run", help="run a scene (YAML) as an FMI co-simulation",
                 description="Run a scene: build its FMUs (cached), step them with the scene's master "
                             "algorithm, stream the trace to CSV and print a summary.")
    add_scene(p)
    add_sets(p, "override a scene value, e.g. master.step=5e-4 or components.pid1.params.Kp=40; repeatable")
    add_out(p, "output directory (default runs/<scene name>)")
    p.add_argument("--plot", action="store_true", help="also write <scene>.png with the recorded outputs")
    p.add_argument("--animate", action="store_true", help="also write <scene>.gif of the platform and legs")
    p.add_argument("--reference", action="store_true",
                   help="also integrate the scene as one ODE (CVODES; SciPy's LSODA from event to event where "
                        "components have events) into <scene>_reference.csv and report the co-simulation's error "
                        "against it (catalog and Modelica components, not external FMUs)")
    p.add_argument("--check", action="store_true", help="only validate the scene and print what it contains")
    add_trace_format(p, "trace file format: a plain CSV (default), a CSV with the metadata in '# key: value' "
                        "comment lines, Parquet (<scene>.parquet, metadata in its schema) or NumPy (<scene>.npy, "
                        "float64 rows, column names in the sidecar)")
    add_report(p, "also write <scene>.html: an interactive report (plots, animation, statistics) that opens "
                  "offline in a browser")
    p.add_argument("--engine", metavar="{auto,compiled}", help="override master.engine")
    add_cache(p)
    p.add_argument("--call-timeout", metavar="SECONDS", type=float, default=None,
                   help="end the run as 'hung' when one FMI call takes longer (default $RPR_COSIM_CALL_TIMEOUT or 60)")
    p.add_argument("--max-trace", metavar="SIZE", default=None,
                   help="refuse a run whose trace would be larger, e.g. 20GB (default $RPR_COSIM_MAX_TRACE or 4GB)")


def _compare(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "compare", "compare_verb:_compare",
                 help="differences between two traces (e.g. co-simulation vs reference or rig)",
                 description="Compare two rpr-cosim traces variable by variable.")
    p.add_argument("test", type=Path, help="trace under test (CSV written by rpr-cosim), or the output directory "
                                           "of a batch: then every run of it is compared with REFERENCE")
    p.add_argument("reference", type=Path, help="reference trace, interpolated onto the first one's instants")
    add_only(p, "compare only variables matching this glob, e.g. 'mech.platform.*'; repeatable", "PATTERN")
    p.add_argument("--plot", type=Path, metavar="FILE", help="also write a PNG of the worst variables")
    add_tol(p, "exit with code 1 when a relative error (max |diff| / range) exceeds REL", default=None)
    p.add_argument("--most", type=int, default=None, metavar="N", help="show the N worst variables only")
    p.add_argument("--allow-failed", action="store_true",
                   help="compare even when a trace's run did not end 'ok' (failed, out_of_limits or unstable by a "
                        "guard, interrupted, unfinished)")
    p.add_argument("--allow-partial", action="store_true",
                   help="compare even when the traces overlap over less than either trace's time span")
    p.add_argument("--events", action="append", default=None, metavar="SIGNAL",
                   help="an event counter or time-of-the-last-event signal: match the events, report their time "
                        "error and measure values between events; repeatable")
    p.add_argument("--event-tol", type=float, default=None, metavar="S",
                   help="with --tol: the largest event-time error [s] (default: the runs' event time tolerance, REL "
                        "times 0.1 s)")
    p.add_argument("--allow-different-scenes", action="store_true",
                   help="compare even when the sidecars' scene hashes differ in what is simulated (components, "
                        "parameters, connections, inputs); differences in the master's settings are always allowed")


def _fit(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "fit", "fit_verb:_fit", help="estimate a scene's parameters from a recording (least squares, "
                                        "confidence intervals), write the calibrated scene and check it",
                 description="Fit parameters of a scene to recorded data and check the calibrated co-simulation.")
    add_scene(p, "scene whose parameters are fitted (its recorded outputs are matched with the data's columns)")
    p.add_argument("--data", type=Path, required=True, metavar="FILE",
                   help="the recording: CSV or Parquet with a 'time' column [s] and the scene's output names")
    p.add_argument("--params", required=True, metavar="LIST",
                   help="comma-separated COMPONENT.PARAMETER names, globs allowed: 'motor*.R,rig.leg[*].raw_zero'")
    p.add_argument("--signals", metavar="LIST", help="comma-separated signals to fit (default: every recorded "
                                                     "output of the scene that the data has)")
    add_sets(p, "scene override before the fit, as for run (repeatable); kept in the calibrated scene")
    add_out(p, "output directory (default runs/<scene>_fit)")
    p.add_argument("--max-evaluations", type=int, default=100, metavar="N", help="residual evaluations at most "
                                                                                  "(default 100)")
    p.add_argument("--substeps", type=int, default=None, metavar="N",
                   help="RK4 substeps per data interval (default: from the model's fastest eigenvalue)")
    p.add_argument("--no-check", action="store_true", help="do not run the co-simulations that check the fit")


def _study(sub: argparse._SubParsersAction) -> None:
    studies = add_actions(sub, "study", "study", "STUDY",
                          help="measured studies of master algorithms (stability maps)",
                          description="Studies that run a scene many times and chart the outcome.")
    s = add_verb(studies, "stability", "study_verb:_stability",
                 help="stable/unstable map over communication step x one scene parameter",
                 description="Run the scene over a log grid of communication steps and values of one "
                             "parameter, for each master algorithm variant, and chart where it is stable.")
    add_scene(s, "scene file, e.g. scenarios/two_mass.yaml")
    s.add_argument("--vary", required=True, metavar="PATH=LO:HI",
                   help="scene parameter and its range (log axis), e.g. components.mass2.params.kc=1:1e4")
    s.add_argument("--steps", default="1e-3:0.5", metavar="LO:HI", help="communication steps [s] (log axis; "
                                                                         "default 1e-3:0.5)")
    s.add_argument("--n", type=int, default=12, metavar="N", help="grid points per axis (default 12)")
    add_variants(s, "algorithm variant, e.g. jacobi/hold or gauss_seidel/linear; repeatable "
                    "(default: jacobi and gauss_seidel, hold and linear)")
    add_out(s, "output directory (default runs/<scene>_stability)")
    add_report(s, "also write <scene>_stability.html: the map with hover values, opening offline")
    add_cache(s, STUDY_CACHE_HELP)
    q = add_verb(studies, "precision", "study_verb:_precision",
                 help="error against cost (work-precision) of master algorithm variants",
                 description="Run the scene for every algorithm variant, fixed-step ones over the "
                             "communication step and variable-step ones (adaptive, ecco) over their "
                             "tolerance, measure each run against the scene's monolithic reference (max "
                             "error relative to each signal's range) and its cost (wall time of the "
                             "stepping loop, doSteps, rejected steps, rollbacks), print the table and draw "
                             "the work-precision chart; the peer master ecospy is a point where it is "
                             "installed.  Runs go through the batch runner: resumable in --out.")
    add_scene(q, CATALOG_SCENE_HELP)
    q.add_argument("--steps", metavar="H,H,...", help="communication steps [s], each halving the previous "
                                                      "(default: 4x the scene's step down to 1/8 of it)")
    q.add_argument("--rtols", metavar="R,R,...", help="tolerances (option rtol) of the variable-step algorithms "
                                                      "(default: 1e-2,1e-3,1e-4,1e-5)")
    add_variants(q, "algorithm variant, e.g. gauss_seidel/linear or adaptive; repeatable (default: every "
                    "fixed-step algorithm with hold and linear, every variable-step one with its own linear "
                    "inputs; a variant the scene refuses is a row with the reason)")
    q.add_argument("--stop", type=float, metavar="T", help="simulated time per run [s] (default: the scene's)")
    add_only(q)
    add_sets(q, "override a scene value in every run, e.g. components.mech.rate=4 (multirate)")
    add_tol(q, "report the cheapest run whose worst relative error is within REL (default 1e-3)")
    q.add_argument("--workers", type=int, default=1, metavar="N",
                   help="runs at once on local processes (default 1: the wall times are the cost measured, and "
                        "runs sharing cores slow each other)")
    q.add_argument("--no-peer", dest="peer", action="store_false", help="no ecospy point")
    add_report(q, "also write <scene>_precision.html: the work-precision chart with hover values, opening offline")
    add_out(q, "output directory, runs kept in runs/ and reused when the study is repeated (default "
               "runs/<scene>_precision)")
    add_cache(q, STUDY_CACHE_HELP)
    f = add_verb(studies, "fidelity", "study_verb:_fidelity",
                 help="error and cost of every fidelity combination; the cheapest within --tol",
                 description="Run the scene with every combination of its models' fidelity levels, "
                             "measure each against the most detailed combination and its cost, and name the "
                             "cheapest combination within the tolerance.")
    add_scene(f, CATALOG_SCENE_HELP)
    add_tol(f, "largest error relative to each signal's range (default 1e-3)")
    add_only(f)
    add_sets(f, "override a scene value first, e.g. stop_time=1")
    add_cache(f, STUDY_CACHE_HELP)


def _ssp(sub: argparse._SubParsersAction) -> None:
    verbs = add_actions(sub, "ssp", "ssp_verb",
                        help="export a scene as an SSP 1.0 archive (run one with 'run FILE.ssp')",
                        description="Scenes as SSP 1.0 archives (System Structure and Parameterization).")
    e = add_verb(verbs, "export", "ssp_verb:_export",
                 help="write SCENE as FILE.ssp (FMUs, parameter set, connections, master)")
    add_scene(e)
    add_out(e, "archive to write (default <scene name>.ssp here)", "-o")
    add_sets(e, "override a scene value before export; repeatable")
    e.add_argument("--force", action="store_true", help="replace an existing archive")
    add_cache(e)


def _board(sub: argparse._SubParsersAction) -> None:
    verbs = add_actions(sub, "board", "board_verb",
                        help="the rig's I/O daemon (BeagleBone), its key, its build, and the virtual board",
                        description="Hardware in the loop: the BeagleBone I/O daemon and the virtual board.")
    k = add_verb(verbs, "keygen", "board_verb:_keygen", help="make a new shared key file (owner-only permissions)")
    k.add_argument("file", type=Path)
    b = add_verb(verbs, "build", "board_verb:_build", help="write the daemon binary for this machine or the BeagleBone (armhf)")
    _board_add_target(b, "host (this machine) or armhf (BeagleBone Black, statically linked; default host)")
    add_out(b, "file to write (default ./rpr-board-TARGET)")
    for name, handler, text in (("serve", "board_verb:_serve", "run the I/O daemon on the board's pins"),
                                ("virtual", "board_verb:_virtual", "run the daemon on a fake sysfs tree with a simulated rig "
                                                      "behind it")):
        s = add_verb(verbs, name, handler, help=text)
        s.add_argument("--key", type=Path, required=True, help="shared key file (rpr-cosim board keygen)")
        s.add_argument("--listen", default="127.0.0.1:5005", metavar="ADDR:PORT",
                       help="UDP address (default 127.0.0.1:5005, loopback only; port 0 picks a free one)")
        s.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="daemon ticks per second (1000)")
        s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
        s.add_argument("--rt-priority", type=int, default=0, metavar="P",
                       help="run under SCHED_FIFO at priority P (1..99; needs root or CAP_SYS_NICE): keeps a 1 kHz "
                            "loop on time on a busy machine")
        s.add_argument("-v", "--verbose", action="store_true", help="log sessions and faults")
        _board_add_target(s, "the daemon's build: host, or armhf under qemu-user (tests, benchmarks; default host)")
        if name == "serve":
            s.add_argument("--root", type=Path, default=Path("/"), help="sysfs root (default /; a fake tree in tests)")
            s.add_argument("--gpio", default="auto", choices=("auto", "sysfs", "chardev"),
                           help="DIR lines through the GPIO character device or sysfs (default auto: the character "
                                "device when the board has one)")
            s.add_argument("--travel", default=None, metavar="LO,HI",
                           help="calibrated ends of the stroke [ADC counts] for the end and range checks")
        else:
            s.add_argument("--tree", type=Path, default=None, help="create the fake tree here (default: a temp dir, "
                                                                   "removed at exit)")
            _board_add_plant(s, "rig")
            for flag, what in (("--stuck", "sensor of leg N frozen"), ("--unplug", "pot of leg N unplugged"),
                               ("--driver-fault", "driver of leg N gives no voltage")):
                s.add_argument(flag, type=int, action="append", default=[], metavar="N", choices=(1, 2, 3), help=what)


    r = add_verb(verbs, "record", "board_verb:_record", help="record the virtual board's plant driven by a test voltage "
                                                "(synthetic time, known true parameters): a trace to replay and fit")
    add_out(r, "trace to write (default runs/record/rig_recording.csv)")
    r.add_argument("--seconds", type=float, default=5.0, metavar="S", help="length of the recording (default 5 s)")
    r.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="samples per second (default 1000)")
    r.add_argument("--current-noise", type=float, default=0.0, metavar="A",
                   help="noise of the motor currents (std dev [A]; fidelity motor)")
    _board_add_plant(r, "motor")


def _board_add_plant(s: argparse.ArgumentParser, fidelity: str) -> None:
    """The virtual plant's options: its model, true parameters, pots, noise and latency."""
    s.add_argument("--fidelity", default=fidelity, choices=("rig", "motor"),
                   help=f"the actuator block: rig (first-order speed lag) or motor (a DC motor per leg; default "
                        f"{fidelity})")
    s.add_argument("--actuator", default="fa200", choices=("fa200", "x"), help="preset of the rig fidelity")
    s.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE",
                   help="a true parameter of the plant's block, e.g. R=4.8 or components.rig.params.R=4.8 "
                        "(repeatable; rpr-cosim fmu show linear_actuator --fidelity motor lists them)")
    s.add_argument("--calibration", action="append", default=[], metavar="LEG:ZERO:FULL",
                   help="leg 1..3 (or 'all') pot: ADC counts at zero stroke and at 0.635 m (repeatable)")
    s.add_argument("--start", default="0.31086,0.35586,0.20428", metavar="L1,L2,L3",
                   help="leg lengths at the start [m] (default: Table 6.12's start pose)")
    s.add_argument("--noise", type=float, default=0.0, metavar="COUNTS", help="ADC noise (std dev, counts)")
    s.add_argument("--latency", type=float, default=0.0, metavar="S", help="sensor latency [s]")
    s.add_argument("--seed", type=int, default=0, help="seed of the noise")


def _board_add_target(p: argparse.ArgumentParser, help: str) -> None:
    """``--target``: the daemon's build, for this machine (host) or the BeagleBone (armhf)."""
    p.add_argument("--target", default="host", choices=("host", "armhf"), help=help)


def _batch(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "batch", "batch_verb:_batch", help="run a sweep or Monte Carlo batch of a scene (local processes or Dask)",
                 description="Run every variant of a scene that a batch file describes, in parallel, "
                             "into one results table; rerunning resumes.")
    p.add_argument("batch", type=Path, help="batch file, e.g. scenarios/batch_pid_gains.yaml")
    p.add_argument("--workers", type=int, metavar="N", help="worker processes (default: one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run on the Dask cluster of this scheduler, "
                                                           "e.g. tcp://10.0.0.5:8786")
    p.add_argument("--dask", action="store_true", help="start a Dask LocalCluster of --workers processes")
    add_out(p, "output directory (default runs/<batch name>)")
    p.add_argument("--sort", metavar="COLUMN", help="sort the printed table by this column (default: "
                                                    "report.sort, or the first metric)")
    p.add_argument("--descending", action="store_true", help="largest first")
    p.add_argument("--most", type=int, default=20, metavar="N", help="print N rows at most (default 20)")
    p.add_argument("--no-plots", action="store_true", help="do not write the charts")
    p.add_argument("--no-reuse", action="store_true", help="load every FMU again for each run instead of "
                                                           "resetting the instances a worker keeps")
    p.add_argument("--check", action="store_true", help="only validate the batch and list its runs")
    add_trace_format(p, "each run's trace format (default npy: float64 rows, numpy.load reads them, column names "
                        "in the sidecar; csv for text); parquet also writes results.parquet", default="npy")
    add_report(p, "also write report.html: the sortable results table and charts, each point linked to "
                  "its run's own report")
    add_cache(p)


def _report(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "report", "report_verb:_report",
                 help="write an interactive HTML report of a run, batch or study (opens offline)",
                 description="Write one self-contained HTML file (Plotly embedded) for what a run, batch or "
                             "study wrote: zoomable linked plots with units, the animation, the statistics; "
                             "for a batch the sortable table and clickable charts; for a study its chart.")
    p.add_argument("out", type=Path, help="a trace file, a run's directory, a batch's directory or a study's table")
    p.add_argument("-o", "--output", type=Path, help="the HTML file to write (default beside what it reports)")
    p.add_argument("--runs", action="store_true", help="for a batch, also write each run's own report (up to about 2 MB "
                                                        "each, sharing the batch's Plotly library) and link it from the batch's")


def _design(sub: argparse._SubParsersAction) -> None:
    p = add_verb(sub, "design", "design_verb:run", help="the thesis's Chapter 8 design checks, from its inputs and a task's loads",
                 description="Chapter 8's static design calculations (bearing forces, bending and equivalent moments, "
                             "permissible stress, minimum shaft diameter, clamp force, actuator force/speed/power) "
                             "from the thesis's inputs and from the loads of tasks (--task) or recorded runs (--trace).")
    p.add_argument("--task", action="append", default=[], type=Path, metavar="FILE",
                   help="a task file (see `rpr-cosim task`); repeatable")
    p.add_argument("--trace", action="append", default=[], type=Path, metavar="FILE",
                   help="a run's trace recording <mech>.leg[1..3].f and .s; repeatable")
    p.add_argument("--drive", default=None, metavar="NAME",
                   help="actuator rating to compare with: table67 (the simulated motor) or fa200 (the rig); "
                        "default: the first task's, else table67")
    p.add_argument("--out", type=Path, default=Path("out/design"), metavar="DIR", help="output directory (default out/design)")
    p.add_argument("--plot", action="store_true", help="save each case's loads over time against their limits (PNG)")


def _task(sub: argparse._SubParsersAction) -> None:
    actions = add_actions(sub, "task", "task_action", help="plan a task through waypoints and check it before it runs",
                          description="Plan a motion through task-space waypoints (ruckig, toppra or a timed spline) "
                                      "and check it against the workspace, singularities and the actuators.")
    for name, handler, text in (("check", "task_verb:_check", "plan and check a task; exit 1 with a one-line refusal"),
                                ("plan", "task_verb:_plan", "plan a task and write its samples as CSV")):
        p = add_verb(actions, name, handler, help=text, description=text)
        p.add_argument("task", type=Path, help="task file (YAML), e.g. scenarios/tasks/pick_and_place.yaml")
        p.add_argument("--out", type=Path, default=None, metavar="DIR", help="output directory (default out/task)")
        p.add_argument("--dt", default="1e-3", metavar="S", help="sampling period of the check and the CSV (default 1e-3 s)")
        if name == "check":
            p.add_argument("--plot", action="store_true", help="draw the path over the workspace and det J maps (PNG)")


#: The verbs in the order they appear in ``--help``.
VERBS = (_analyze, _fmu, _run, _compare, _fit, _study, _ssp, _board, _batch, _report, _design, _task)


def add_verbs(sub: argparse._SubParsersAction) -> None:
    """Every verb's parser under ``sub``."""
    for declare in VERBS:
        declare(sub)
