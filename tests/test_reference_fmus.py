"""The Modelica Reference FMUs (built from their source, see ``conftest.reference_fmus``) in our
scenes against FMPy's ``simulate_fmu`` of the same FMU with the same communication step: every
variable FMPy can record (all numeric types, arrays flattened row-major) equal to 1e-12.

Coupling-delay convention of the coupled case (VanDerPol -> Feedthrough; FMPy runs one FMU, so the
VanDerPol trace is fed to Feedthrough as FMPy's input signal): under Jacobi, Feedthrough's input
over [t_k, t_k+1] is VanDerPol's output at t_k (FMPy's own convention: inputs applied at t_k);
under Gauss-Seidel (VanDerPol first) it is VanDerPol's output at t_k+1, i.e. FMPy gets the signal
shifted one step earlier; at t_0 both see the output at t_0 (initialisation propagates it).
"""
from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from cosim.errors import UserError
from cosim.run.execute import run
from cosim.scenario import SceneError
from cosim.scenario import from_dict as _from_dict
from cosim.slaves.description import describe_fmu
from cosim.slaves.typedio import element_names

fmpy = pytest.importorskip("fmpy")


def from_dict(data, **kw):
    """The scene, with the fixed-step master it had before a scene without an algorithm got the
    tolerance's choice (these tests are about the FMUs' I/O at fixed communication points)."""
    master = dict(data.get("master") or {})
    master.setdefault("algorithm", "gauss_seidel")
    return _from_dict({**data, "master": master}, **kw)


ATOL = 1e-12

#: name -> (communication step [s], stop time [s] or None for the FMU's default experiment, FMI versions)
CASES = {
    "BouncingBall": (0.01, None, ("2.0", "3.0")),
    "Dahlquist": (0.1, None, ("2.0", "3.0")),
    "VanDerPol": (0.01, None, ("2.0", "3.0")),
    "Feedthrough": (0.1, 2.0, ("2.0", "3.0")),
    "Stair": (0.2, None, ("2.0", "3.0")),
    "Resource": (0.1, 1.0, ("2.0", "3.0")),
    "StateSpace": (0.1, 2.0, ("3.0",)),
}
#: start values and parameters that move the models away from their defaults (FMPy gets the same)
STARTS = {
    "VanDerPol": ({"x0": 1.5}, {"mu": 1.7}),
    "Dahlquist": ({"x": 2.0}, {"k": 0.5}),
    "BouncingBall": ({"h": 2.0}, {"e": 0.6}),
    "Feedthrough": ({"Float64_continuous_input": 3.5, "Int32_input": -7, "Boolean_input": True,
                     "Enumeration_input": 2, "String_input": "hello"}, {"Float64_tunable_parameter": 4.25}),
    "StateSpace": ({"u": [1.0, -2.0, 0.5]}, {"A": [[-1, 0.5, 0], [0, -2, 0], [0.25, 0, -3]], "D": [[0, 0, 0]] * 3}),
}
FMI3_EXTRA = {"Feedthrough": ({"Float32_continuous_input": 0.25, "Int8_input": -5, "UInt16_input": 65535,
                               "Int64_input": -(2 ** 40), "UInt64_input": 2 ** 40}, {})}


def _recordable(path, fmi):
    """Every variable FMPy records (numbers of any type; not time, String, Binary or Clock)."""
    md = fmpy.read_model_description(str(path))
    skip = {"String", "Binary", "Clock"}
    return [v.name for v in md.modelVariables if v.causality != "independent" and v.type not in skip]


def _columns(result, prefix: str) -> dict[str, np.ndarray]:
    """FMPy's structured result as flat columns named like our trace (``prefix.var[i,j]``)."""
    out = {}
    for name in result.dtype.names:
        if name == "time":
            continue
        col = np.asarray(result[name], dtype=float)
        shape = col.shape[1:]
        flat = col.reshape(len(col), -1)
        for j, el in enumerate(element_names(name, shape)):
            out[f"{prefix}.{el}"] = flat[:, j]
    return out


def _fmpy_values(values: dict) -> dict:
    return {k: np.ravel(v).tolist() if isinstance(v, list) else v for k, v in values.items()}


def _assert_equal_traces(trace, ref_time, ref_cols, names):
    assert len(trace.time) == len(ref_time), (len(trace.time), len(ref_time))
    np.testing.assert_allclose(trace.time, ref_time, rtol=0, atol=ATOL)
    for name in names:
        ours, theirs = trace[name], ref_cols[name]
        scale = np.maximum(1.0, np.abs(theirs))
        worst = float(np.max(np.abs(ours - theirs) / scale))
        assert worst <= ATOL, f"{name}: {worst:.3g} from FMPy"


def _case_params():
    for model, (_, _, versions) in CASES.items():
        for v in versions:
            yield pytest.param(model, v, id=f"{model}-fmi{v[0]}")


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("model,fmi", list(_case_params()))
def test_single_fmu_matches_fmpy(reference_fmus, model, fmi, algorithm):
    path = reference_fmus[f"{fmi}/{model}"]
    step, stop, _ = CASES[model]
    start, params = STARTS.get(model, ({}, {}))
    if fmi == "3.0":
        start = {**start, **FMI3_EXTRA.get(model, ({}, {}))[0]}
    names = _recordable(path, fmi)
    comp = {"fmu": str(path), "start": start, "params": params}
    scene = {"name": "ref", "components": {"m": comp}, "master": {"algorithm": algorithm, "step": step},
             "outputs": [f"m.{n}" for n in names] + (["m.String_output"] if "String_input" in start else [])}
    if stop is not None:
        scene["stop_time"] = stop
    res = run(from_dict(scene))
    md = fmpy.read_model_description(str(path))
    t_stop = stop if stop is not None else md.defaultExperiment.stopTime
    # FMI 3.0 with event mode (BouncingBall, Stair, ...): our run ends its steps at the FMU's events
    # and writes two rows at each, as FMPy does with event mode and early return
    events = fmi == "3.0" and bool(getattr(md.coSimulation, "hasEventMode", False))
    ref = fmpy.simulate_fmu(str(path), fmi_type="CoSimulation", output_interval=step, stop_time=float(t_stop),
                            output=names, start_values=_fmpy_values({**params, **start}), use_event_mode=events,
                            early_return_allowed=events)
    if res.status == "stopped":  # FMPy takes one more step after a terminate request in an event iteration
        ref = ref[ref["time"] <= res.trace.time[-1] + ATOL]
    cols = _columns(ref, "m")
    _assert_equal_traces(res.trace, ref["time"], cols, [c for c in res.trace.names])
    assert sorted(res.trace.names) == sorted(cols)  # every variable FMPy records, and no other
    if model == "Stair":  # asks to stop when its counter reaches 10, at t = 9 s
        assert res.status == "stopped" and res.reason.startswith("stopped by m at t = 9 s"), res.reason
        assert res.trace.time[-1] == pytest.approx(9.0, abs=ATOL) and res.trace["m.counter"][-1] == 10
    else:
        assert res.status == "ok", res.reason
    if "String_input" in start:  # Feedthrough copies its String input to its output
        assert res.trace.text["m.String_output"] == [(0.0, "hello")]


@pytest.mark.parametrize("model", ["BouncingBall", "VanDerPol"])
def test_compiled_loop_takes_float64_only_fmus(reference_fmus, model):
    """A Float64-only scene keeps the compiled loop, and it matches FMPy too (BouncingBall in event
    mode, its steps ended at its events, as FMPy with event mode and early return)."""
    path = reference_fmus[f"3.0/{model}"]
    step = CASES[model][0]
    res = run(from_dict({"name": "ref", "stop_time": 1.0, "master": {"step": step, "engine": "compiled"},
                         "components": {"m": {"fmu": str(path)}}}))
    assert res.stats["engine"] == "compiled"
    events = bool(getattr(fmpy.read_model_description(str(path)).coSimulation, "hasEventMode", False))
    assert events == (model == "BouncingBall")
    ref = fmpy.simulate_fmu(str(path), fmi_type="CoSimulation", output_interval=step, stop_time=1.0,
                            output=[n.split(".", 1)[1] for n in res.trace.names], use_event_mode=events,
                            early_return_allowed=events)
    _assert_equal_traces(res.trace, ref["time"], _columns(ref, "m"), res.trace.names)


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss_seidel"])
@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_coupled_vanderpol_feedthrough_matches_fmpy(reference_fmus, fmi, algorithm):
    vdp, ft = reference_fmus[f"{fmi}/VanDerPol"], reference_fmus[f"{fmi}/Feedthrough"]
    h, stop = 0.01, 3.0
    res = run(from_dict({"name": "coupled", "stop_time": stop, "components": {"vdp": {"fmu": str(vdp)},
                                                                              "ft": {"fmu": str(ft)}},
                         "connections": ["vdp.x0 -> ft.Float64_continuous_input"],
                         "master": {"algorithm": algorithm, "step": h, "order": ["vdp", "ft"]},
                         "outputs": ["vdp.x0", "vdp.x1", "ft.Float64_continuous_output", "ft.Int32_output"]}))
    assert res.status == "ok", res.reason
    a = fmpy.simulate_fmu(str(vdp), fmi_type="CoSimulation", output_interval=h, stop_time=stop, output=["x0", "x1"])
    x0 = np.asarray(a["x0"], dtype=float)
    fed = x0 if algorithm == "jacobi" else np.concatenate([x0[1:], x0[-1:]])  # see the module docstring
    signal = np.array(list(zip(a["time"], fed)), dtype=[("time", float), ("Float64_continuous_input", float)])
    b = fmpy.simulate_fmu(str(ft), fmi_type="CoSimulation", output_interval=h, stop_time=stop, input=signal,
                          output=["Float64_continuous_output", "Int32_output"])
    cols = {**_columns(a, "vdp"), **_columns(b, "ft")}
    if algorithm == "gauss_seidel":
        cols["ft.Float64_continuous_output"][0] = x0[0]  # at t_0 both see the output at t_0
    _assert_equal_traces(res.trace, a["time"], cols, res.trace.names)
    assert res.trace["ft.Float64_continuous_output"][5] != res.trace["ft.Float64_continuous_output"][4]


def test_default_experiment_and_scene_start_time(reference_fmus):
    """No stop_time or step in the scene: BouncingBall's DefaultExperiment (stop 3 s, step 0.01 s);
    the scene's start_time and stop_time win over it; FMPy run from the same start agrees."""
    path = reference_fmus["3.0/BouncingBall"]
    res = run(from_dict({"name": "bb", "components": {"m": {"fmu": str(path)}}}))
    grid = np.round(res.trace.time / 0.01, 6)
    assert res.trace.time[-1] == pytest.approx(3.0, abs=ATOL) and len(np.unique(grid[grid == np.round(grid)])) == 301
    res = run(from_dict({"name": "bb", "start_time": 0.5, "stop_time": 1.5, "components": {"m": {"fmu": str(path)}},
                         "outputs": ["m.h", "m.v"]}))
    assert res.trace.time[0] == 0.5 and res.trace.time[-1] == pytest.approx(1.5, abs=ATOL)
    ref = fmpy.simulate_fmu(str(path), fmi_type="CoSimulation", start_time=0.5, output_interval=0.01, stop_time=1.5,
                            output=["h", "v"], use_event_mode=True, early_return_allowed=True)
    _assert_equal_traces(res.trace, ref["time"], _columns(ref, "m"), ["m.h", "m.v"])


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_stop_request_cli_exit_code_and_sidecar(reference_fmus, tmp_path, fmi):
    from cosim import cli

    scene = tmp_path / "stair.yaml"
    scene.write_text(f"name: stair\nmaster: {{algorithm: gauss_seidel}}\ncomponents:\n  s: {{fmu: {reference_fmus[f'{fmi}/Stair']}}}\n")
    assert cli.main(["run", str(scene), "--out", str(tmp_path / "out")]) == 0
    side = json.loads((tmp_path / "out" / "stair.json").read_text())
    assert side["status"] == "stopped" and side["reason"].startswith("stopped by s at t = 9 s")


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_stop_request_in_the_compiled_loop(reference_fmus, fmi):
    """Nothing typed recorded: Stair runs in the compiled loop, which hands the stop request (FMI 3.0
    terminateSimulation, FMI 2.0 Discard + fmi2Terminated) back; the end point t = 9 s is recorded.
    FMI 3.0 Stair without event mode (``inputs: linear``: event mode needs held inputs) asks in its
    doStep; in event mode (the default) it returns early at each step of its counter, the loop
    writes two rows there, and asks to stop in the event iteration at 9 s."""
    master = {"engine": "compiled", "output_interval": 2.0}
    scene = {"name": "stair", "outputs": [], "components": {"s": {"fmu": str(reference_fmus[f"{fmi}/Stair"])}}}
    res = run(from_dict({**scene, "master": {**master, **({"inputs": "linear"} if fmi == "3.0" else {})}}))
    assert res.stats["engine"] == "compiled"
    assert res.status == "stopped" and res.reason.startswith("stopped by s at t = 9 s"), res.reason
    np.testing.assert_allclose(res.trace.time, [0, 2, 4, 6, 8, 9], rtol=0, atol=ATOL)
    if fmi == "3.0":
        res = run(from_dict({**scene, "master": master}))
        assert res.stats["engine"] == "compiled" and res.stats["events"]["handled"] == 9
        assert res.status == "stopped" and res.reason == ("stopped by s at t = 9 s: it asked to terminate the "
                                                          "simulation in its event iteration"), res.reason
        np.testing.assert_allclose(res.trace.time, [0] + [t for t in range(1, 10) for _ in (0, 1)], rtol=0, atol=ATOL)


def test_string_and_binary_are_recorded_as_text_in_the_csv(reference_fmus, tmp_path):
    """Feedthrough copies its String and Binary inputs to its outputs; the CSV keeps them as text
    events that read_trace gives back."""
    from cosim.trace.traces import read_trace

    res = run(from_dict({"name": "txt", "stop_time": 0.3, "master": {"step": 0.1},
                         "components": {"f": {"fmu": str(reference_fmus["3.0/Feedthrough"]),
                                              "start": {"String_input": "grüße", "Binary_input": "00ff10"}}},
                         "outputs": ["f.String_output", "f.Binary_output", "f.Int8_output"]}), out_dir=tmp_path)
    back = read_trace(res.trace_path)
    assert back.text == res.trace.text == {"f.String_output": [(0.0, "grüße")], "f.Binary_output": [(0.0, "00ff10")]}
    assert back.names == ["f.Int8_output"] and len(back.time) == 4


# --- start values and parameters -------------------------------------------------------------------
def _check(reference_fmus, comp: dict, key: str = "3.0/VanDerPol", **extra):
    comp = {"fmu": str(reference_fmus[key]), **comp}
    return from_dict({"name": "x", "stop_time": 1, "master": {"step": 0.1}, "components": {"m": comp}, **extra})


def test_start_of_an_exact_output_is_accepted(reference_fmus):
    assert _check(reference_fmus, {"start": {"x0": 1.5}}).components["m"].start == {"x0": 1.5}


@pytest.mark.parametrize("comp,message", [
    ({"start": {"der(x0)": 1.0}}, "'der(x0)' is a local variable computed by the FMU (initial = calculated)"),
    ({"start": {"mu": 2.0}}, "'mu' is a parameter; set it under 'params:'"),
    ({"params": {"x0": 2.0}}, "'x0' is an output (initial = exact), not a parameter; set its start value under 'start:'"),
    ({"params": {"mu": "fast"}}, "parameter mu (Float64) must be a number (Float64), got 'fast'"),
])
def test_bad_start_values_name_the_rule(reference_fmus, comp, message):
    with pytest.raises(SceneError, match=None) as err:
        _check(reference_fmus, comp)
    assert message in str(err.value)


def test_structural_parameter_goes_under_params_and_sizes_arrays(reference_fmus):
    with pytest.raises(SceneError) as err:
        _check(reference_fmus, {"start": {"n": 2}}, "3.0/StateSpace")
    assert "'n' is a structural parameter (it sizes arrays and is set in configuration mode); set it under " \
           "'params:'" in str(err.value)
    with pytest.raises(SceneError) as err:  # n = 2 makes A 2 x 2: nine values no longer fit
        _check(reference_fmus, {"params": {"n": 2, "A": [1, 0, 0, 0, 1, 0, 0, 0, 1]}}, "3.0/StateSpace")
    assert "parameter A (Float64, shape 2x2) needs 4 values, got 9" in str(err.value)
    scene = _check(reference_fmus, {"params": {"n": 2, "A": [[1, 0], [0, 1]]}}, "3.0/StateSpace")
    assert scene.components["m"].description.variables["x"].shape == (2,)


def test_structural_parameter_set_in_configuration_mode(reference_fmus):
    """StateSpace refuses every single-value fmi3SetUInt64 of m, n or r (its ASSERT_NVALUES runs
    after the index moved on: "Expected nValues >= 2 but was 1"); we call it in configuration mode as
    FMI 3.0 asks, and the FMU's own reason reaches the user."""
    with pytest.raises(UserError, match=r"setting structural parameter n failed .*Expected nValues >= 2 but was 1"):
        run(_check(reference_fmus, {"params": {"n": 3}}, "3.0/StateSpace"))


def _interfaces_fmu(tmp_path, kinds: str):
    fmu = tmp_path / "m.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.writestr("modelDescription.xml", f'<?xml version="1.0" encoding="UTF-8"?>\n<fmiModelDescription '
                                           f'fmiVersion="3.0" modelName="m" instantiationToken="x">{kinds}'
                                           f'<ModelVariables><Float64 name="t" valueReference="0" '
                                           f'causality="independent"/></ModelVariables><ModelStructure/>'
                                           f'</fmiModelDescription>')
    return fmu


@pytest.mark.parametrize("kinds,interface,message", [
    ('<ScheduledExecution modelIdentifier="m"/>', None,
     "has scheduled execution only; rpr-cosim runs co-simulation and model-exchange FMUs (Scheduled Execution"),
    ('<ModelExchange modelIdentifier="m"/>', "co_simulation", "interface co_simulation asked, but the FMU has model "
                                                              "exchange only"),
    ('<CoSimulation modelIdentifier="m"/>', "model_exchange", "interface model_exchange asked, but the FMU has "
                                                              "co-simulation only"),
])
def test_interface_kinds_are_named(tmp_path, kinds, interface, message):
    with pytest.raises(UserError) as err:
        describe_fmu(_interfaces_fmu(tmp_path, kinds), interface)
    assert message in str(err.value)


def test_model_exchange_only_is_described_as_such(tmp_path):
    both = '<ModelExchange modelIdentifier="m"/><CoSimulation modelIdentifier="m"/>'
    assert describe_fmu(_interfaces_fmu(tmp_path, '<ModelExchange modelIdentifier="m"/>')).interface == "model exchange"
    assert describe_fmu(_interfaces_fmu(tmp_path, both)).interface == "co-simulation"
    assert describe_fmu(_interfaces_fmu(tmp_path, both), "model_exchange").interface == "model exchange"


# --- type checks of connections -----------------------------------------------------------------------
#: Feedthrough (FMI 3.0) variable stem per type, with its integer range (None: not an integer)
FT_TYPES = {"Float32": ("Float32_continuous", None), "Float64": ("Float64_continuous", None),
            "Int8": ("Int8", (-2 ** 7, 2 ** 7 - 1)), "UInt8": ("UInt8", (0, 2 ** 8 - 1)),
            "Int16": ("Int16", (-2 ** 15, 2 ** 15 - 1)), "UInt16": ("UInt16", (0, 2 ** 16 - 1)),
            "Int32": ("Int32", (-2 ** 31, 2 ** 31 - 1)), "UInt32": ("UInt32", (0, 2 ** 32 - 1)),
            "Int64": ("Int64", (-2 ** 63, 2 ** 63 - 1)), "UInt64": ("UInt64", (0, 2 ** 64 - 1)),
            "Boolean": ("Boolean", (0, 1)), "String": ("String", None), "Binary": ("Binary", None),
            "Enumeration": ("Enumeration", (-2 ** 63, 2 ** 63 - 1))}  # FMI 3.0 stores enumerations as Int64
NUMERIC = {t for t in FT_TYPES if t not in ("String", "Binary")}


def _allowed(a: str, b: str) -> bool:
    """The documented conversions (docs/how-to/external-fmu.md), written out independently."""
    if a not in NUMERIC or b not in NUMERIC or b in ("Enumeration", "Boolean"):
        return False
    if b in ("Float32", "Float64"):
        return True
    ra, rb = FT_TYPES[a][1], FT_TYPES[b][1]
    return ra is not None and rb[0] <= ra[0] and ra[1] <= rb[1]


def _pair_scene(reference_fmus, a: str, b: str, suffix: str = ""):
    ft = str(reference_fmus["3.0/Feedthrough"])
    return {"name": "pair", "stop_time": 1, "master": {"step": 0.1},
            "components": {"f": {"fmu": ft}, "g": {"fmu": ft}},
            "connections": [f"f.{FT_TYPES[a][0]}_output -> g.{FT_TYPES[b][0]}_input{suffix}"]}


@pytest.mark.parametrize("b", list(FT_TYPES))
@pytest.mark.parametrize("a", list(FT_TYPES))
def test_type_pair_connection(reference_fmus, a, b):
    lhs, rhs = f"f.{FT_TYPES[a][0]}_output", f"g.{FT_TYPES[b][0]}_input"
    if a == b:
        assert len(from_dict(_pair_scene(reference_fmus, a, b)).connections) == 1
        return
    with pytest.raises(SceneError) as err:
        from_dict(_pair_scene(reference_fmus, a, b))
    (problem,) = [p for p in err.value.problems if p.severity == "error"]
    assert problem.file.endswith("<dict>")
    if _allowed(a, b):
        assert problem.message == f"type mismatch: {lhs} is {a} but {rhs} is {b}; to convert, write " \
                                  f"'{lhs} -> {rhs} as {b}'"
        scene = from_dict(_pair_scene(reference_fmus, a, b, f" as {b}"))
        assert str(scene.connections[0]).endswith(f" as {b}")
    else:
        assert problem.message.startswith(f"type mismatch: {lhs} is {a} but {rhs} is {b}, and {a} -> {b} is no "
                                          f"allowed conversion: ")


def test_type_mismatch_reports_file_and_line(reference_fmus, tmp_path):
    ft = reference_fmus["2.0/Feedthrough"]
    scene = tmp_path / "bad.yaml"
    scene.write_text(f"name: bad\nstop_time: 1\nmaster: {{algorithm: gauss_seidel, step: 0.1}}\ncomponents:\n  f: {{fmu: {ft}}}\n"
                     f"  g: {{fmu: {ft}}}\nconnections:\n  - f.Boolean_output -> g.Float64_continuous_input\n"
                     f"  - f.Float64_continuous_output -> g.Int32_input\n")
    from cosim.scenario import load

    with pytest.raises(SceneError) as err:
        load(scene)
    lines = str(err.value).splitlines()
    assert lines[0].endswith("bad.yaml:8: error: type mismatch: f.Boolean_output is Boolean but "
                             "g.Float64_continuous_input is Real; to convert, write "
                             "'f.Boolean_output -> g.Float64_continuous_input as Real'")
    assert lines[1].endswith("bad.yaml:9: error: type mismatch: f.Float64_continuous_output is Real but "
                             "g.Int32_input is Integer, and Real -> Integer is no allowed conversion: a float does "
                             "not become an integer without a rounding rule; round it in the source model")


def test_array_size_mismatch_and_wrong_as(reference_fmus):
    ss, ft = str(reference_fmus["3.0/StateSpace"]), str(reference_fmus["3.0/Feedthrough"])
    base = {"name": "x", "stop_time": 1, "master": {"step": 0.1}, "components": {"s": {"fmu": ss}, "f": {"fmu": ft}}}
    with pytest.raises(SceneError) as err:
        from_dict({**base, "connections": ["s.y -> f.Float64_continuous_input"]})
    assert "size mismatch: s.y is an array of shape 3 (Float64) but f.Float64_continuous_input is a scalar " \
           "(Float64)" in str(err.value)
    with pytest.raises(SceneError) as err:
        from_dict({**base, "connections": ["f.Int8_output -> f.Int16_input as Int32"]})
    assert "'as Int32' must name the type of f.Int16_input, which is Int16" in str(err.value)


@pytest.mark.parametrize("engine", ["oracle"])
def test_converted_connections_carry_values(reference_fmus, engine):
    """Stair's Int32 counter converted to Float64 and Int64 inputs of Feedthrough arrives unchanged,
    in the event iteration at its time events too (FMI 3.0 event mode: two rows at each)."""
    res = run(from_dict({"name": "conv", "stop_time": 3, "master": {"step": 0.5, "engine": engine},
                         "components": {"s": {"fmu": str(reference_fmus["3.0/Stair"])},
                                        "f": {"fmu": str(reference_fmus["3.0/Feedthrough"])}},
                         "connections": ["s.counter -> f.Float64_continuous_input as Float64",
                                         "s.counter -> f.Int64_input as Int64", "s.counter -> f.Int32_input"],
                         "outputs": ["s.counter", "f.Float64_continuous_output", "f.Int64_output",
                                     "f.Int32_output"]}))
    t = res.trace.time
    left = np.r_[np.diff(t) == 0, False]  # the left limit of the two rows at each event (FMI 3.0 event mode)
    expected = 1 + np.floor(t + 1e-9) - left  # the counter counts the seconds from 1; the event iteration passes it on
    assert left.sum() == 3 and res.stats["events"]["handled"] == 3  # at 1, 2 and 3 s
    for col in res.trace.names:
        np.testing.assert_array_equal(res.trace[col], expected)
