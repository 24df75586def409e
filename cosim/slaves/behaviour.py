"""A behavioural check of a co-simulation FMU, beyond what its XML says: does it do what the FMI
standard says when a master calls it?

Checks (each one a short run on fresh instances, inputs and parameters at their start values):

``instances``      two instances in one process are independent (unless the FMU declares
                   ``canBeInstantiatedOnlyOncePerProcess``)
``determinism``    two fresh instances stepped alike give the same outputs
``no_prior_flag``  the same steps with ``noSetFMUStatePriorToCurrentPoint`` false and true give the
                   same outputs (the flag is a promise about rollback, not a step option)
``state``          get/set/free FMU state with a fresh and with a reused state pointer: setting a
                   saved state and stepping again reproduces the outputs
``reset``          after reset and a new initialisation the same steps give the same outputs
``derivatives``    directional derivatives of the outputs by the inputs at a communication point
                   (inputs a little off their start values) agree with central finite differences
                   (where the FMU provides them; no verdict where two difference steps disagree)
``setters``        every type's setter accepts a parameter's or input's own start value before
                   initialisation, and a parameter set before initialisation keeps that value
``stop_time``      steps at communication points t0 + k h (and half steps where the step size may
                   vary) up to the declared stop time (the last one ending on it exactly) are accepted

Each departure is one line: the function, what the standard says, what the FMU did.  Where a safe
workaround exists it is returned: ``always_no_prior`` (pass ``noSetFMUStatePriorToCurrentPoint =
true`` always: for an FMU whose steps with false differ from those with true) and ``no_rollback``
(an FMU whose restore does not restore is run as one that cannot roll back, so ``adaptive`` and
``iterative`` refuse it with the reason) ``no_reset`` (an FMU whose reset does not reset is loaded
anew for every run of a batch instead of being reset) and ``set_in_init`` (an FMU that forgets
values set before initialisation gets them again in initialisation mode).

:func:`check_in_subprocess` runs the check in a child process (an FMU that crashes cannot take the
run down with it); ``python -m cosim.slaves.behaviour FILE.fmu`` prints the result as JSON.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from ctypes import byref
from pathlib import Path
from ..errors import UserError

STEPS = 5  # steps per short run
REAL = ("Real", "Float64")


class _Fmu:
    """One FMU's description and fresh instances of it (fmpy), both FMI 2.0 and 3.0."""

    def __init__(self, path: Path):
        import fmpy

        self.path = Path(path)
        self.md = fmpy.read_model_description(str(path), validate=False)
        self.fmi3 = self.md.fmiVersion.startswith("3")
        self.cs = self.md.coSimulation
        self.unzip = fmpy.extract(str(path)) if self.cs is not None else None
        de = self.md.defaultExperiment
        self.t0 = float(de.startTime) if de is not None and de.startTime is not None else 0.0
        step = float(de.stepSize) if de is not None and de.stepSize else 1e-3
        stop = float(de.stopTime) if de is not None and de.stopTime else None
        if stop is not None and stop > self.t0:
            step = min(step, (stop - self.t0) / (2 * STEPS))
        self.h = step
        self.vars = list(self.md.modelVariables)
        self.outs = [v for v in self.vars if v.causality == "output" and not getattr(v, "dimensions", None)
                     and v.type in REAL + ("Integer", "Int32", "Boolean")]
        self.ins = [v for v in self.vars if v.causality == "input" and not getattr(v, "dimensions", None)
                    and v.type in REAL]
        self.count = 0
        self.prefix = "fmi3" if self.fmi3 else "fmi2"

    def flag(self, name: str) -> bool:
        return bool(getattr(self.cs, name, False))

    def new(self):
        from fmpy.fmi2 import FMU2Slave
        from fmpy.fmi3 import FMU3Slave

        self.count += 1
        cls = FMU3Slave if self.fmi3 else FMU2Slave
        inst = cls(guid=self.md.guid, unzipDirectory=self.unzip, modelIdentifier=self.cs.modelIdentifier,
                   instanceName=f"check{self.count}")
        inst.instantiate()
        return inst

    def init(self, inst, stop: float | None = None) -> None:
        if self.fmi3:
            inst.enterInitializationMode(startTime=self.t0, stopTime=stop)
        else:
            inst.setupExperiment(startTime=self.t0, stopTime=stop)
            inst.enterInitializationMode()
        inst.exitInitializationMode()

    def outputs(self, inst) -> list[float]:
        vals = []
        for v in self.outs:
            if v.type in REAL:
                vals.append((inst.getFloat64 if self.fmi3 else inst.getReal)([v.valueReference])[0])
            elif v.type == "Boolean":
                vals.append(float(inst.getBoolean([v.valueReference])[0]))
            else:
                vals.append(float((inst.getInt32 if self.fmi3 else inst.getInteger)([v.valueReference])[0]))
        return vals

    def drive(self, inst) -> None:
        """Every real input set away from its start (start + 1, or twice it), so that the steps
        that follow move the state (where inputs at rest leave it at the start)."""
        for v in self.ins:
            if v.type in REAL:
                x = float(v.start) if v.start not in (None, "") else 0.0
                (inst.setFloat64 if self.fmi3 else inst.setReal)([v.valueReference], [2 * x if x else 1.0])

    def step(self, inst, k: int, no_prior: bool, h: float | None = None) -> None:
        h = self.h if h is None else h
        inst.doStep(self.t0 + k * self.h, h, no_prior)

    def run(self, inst, no_prior: bool, first: int = 0, n: int = STEPS) -> list[float]:
        for k in range(first, first + n):
            self.step(inst, k, no_prior)
        return self.outputs(inst)

    def free(self, inst) -> None:
        try:
            inst.terminate()
        except Exception:  # a check may leave the instance in a state where terminate fails
            pass
        try:
            inst.freeInstance()
        except Exception:
            pass


def _float_start(v) -> float | None:
    try:
        return float(v.start)
    except (TypeError, ValueError):
        return None


def _same(a: list[float], b: list[float]) -> bool:
    return len(a) == len(b) and all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b))


def _show(vals: list[float], names) -> str:
    return ", ".join(f"{v.name} = {x:.9g}" for v, x in list(zip(names, vals))[:3]) or "no outputs"


def _failed(exc: Exception) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def check(path: Path) -> dict:
    """Run every check on the FMU ``path``: ``{"departures": [...], "workarounds": {...},
    "checks": [...], "skipped": {check: why}}``."""
    f = _Fmu(path)
    out: dict = {"departures": [], "workarounds": {"always_no_prior": False, "no_rollback": False, "no_reset": False, "set_in_init": False},
                 "checks": [], "skipped": {}}
    if f.cs is None:
        out["skipped"]["all"] = "no co-simulation interface"
        return out
    dep, fn = out["departures"], f.prefix

    def ran(name: str) -> None:
        out["checks"].append(name)

    # reference run: flag true (what a fixed-step master promises)
    a = f.new()
    f.init(a)
    y0 = f.outputs(a)
    try:
        y_true = f.run(a, True)
    except Exception as exc:
        dep.append(f"{fn}DoStep: the standard says a step from the start values at t0 = {f.t0:g} s with h = {f.h:g} s "
                   f"succeeds; the FMU failed ({_failed(exc)})")
        f.free(a)
        return out
    once = f.flag("canBeInstantiatedOnlyOncePerProcess")
    # two instances, determinism
    if once:
        out["skipped"]["instances"] = "canBeInstantiatedOnlyOncePerProcess"
        f.free(a)
    else:
        ran("instances")
        b = f.new()
        f.init(b)
        yb0 = f.outputs(b)
        f.step(a, STEPS, True)  # a moves on; b must not notice
        if not _same(f.outputs(b), yb0):
            dep.append(f"{fn}Instantiate: the standard says instances are independent; stepping one instance changed "
                       f"the outputs of another ({_show(f.outputs(b), f.outs)} instead of {_show(yb0, f.outs)})")
        ran("determinism")
        yb = f.run(b, True)
        if not _same(yb, y_true):
            dep.append(f"{fn}DoStep: the standard expects the same steps from the same start to give the same "
                       f"outputs; two fresh instances gave {_show(y_true, f.outs)} and {_show(yb, f.outs)}")
        f.free(a)
        f.free(b)
    # the flag noSetFMUStatePriorToCurrentPoint
    ran("no_prior_flag")
    c = f.new()
    f.init(c)
    y_false = f.run(c, False)
    f.free(c)
    if not _same(y_false, y_true):
        moved = not _same(y_false, y0)
        dep.append(f"{fn}DoStep: the standard says noSetFMUStatePriorToCurrentPoint only promises that no earlier "
                   f"state will be set; {STEPS} steps with false gave {_show(y_false, f.outs)}, with true "
                   f"{_show(y_true, f.outs)}{'' if moved else ' (with false the FMU did not advance)'}")
        out["workarounds"]["always_no_prior"] = True
    flag = True if out["workarounds"]["always_no_prior"] else False  # the flag a rollback passes
    # state get/set/free
    if f.flag("canGetAndSetFMUstate") or f.flag("canGetAndSetFMUState"):
        ran("state")
        s = f.new()
        f.init(s)
        get = getattr(s, f"{fn}GetFMU{'State' if f.fmi3 else 'state'}")
        try:
            st = s.getFMUState()
            y1 = f.run(s, flag)
            s.setFMUState(st)
            y1b = f.run(s, flag)
            if not _same(y1, y1b):
                dep.append(f"{fn}SetFMU{'State' if f.fmi3 else 'state'}: the standard says setting a saved state "
                           f"restores it; stepping again from the restored state gave {_show(y1b, f.outs)} instead of "
                           f"{_show(y1, f.outs)}")
                out["workarounds"]["no_rollback"] = True
            # reused pointer: the FMU must overwrite the state it points to
            get(s.component, byref(st))
            y2 = f.run(s, flag, STEPS)
            s.setFMUState(st)
            y2b = f.run(s, flag, STEPS)
            if not _same(y2, y2b):
                dep.append(f"{fn}GetFMU{'State' if f.fmi3 else 'state'}: the standard says a non-NULL state pointer is "
                           f"overwritten with the current state; restoring it gave {_show(y2b, f.outs)} instead of "
                           f"{_show(y2, f.outs)}")
                out["workarounds"]["no_rollback"] = True
            s.freeFMUState(st)
            if st.value:
                dep.append(f"{fn}FreeFMU{'State' if f.fmi3 else 'state'}: the standard says the state pointer is set to "
                           f"NULL; the FMU left it")
        except Exception as exc:
            dep.append(f"{fn}Get/SetFMU{'State' if f.fmi3 else 'state'}: the FMU declares canGetAndSetFMUstate; the "
                       f"call failed ({_failed(exc)})")
            out["workarounds"]["no_rollback"] = True
        f.free(s)
    else:
        out["skipped"]["state"] = "canGetAndSetFMUstate is false"
    # reset
    ran("reset")
    r = f.new()
    f.init(r)
    f.drive(r)  # the state moved away from the start, so a reset that keeps it shows
    f.run(r, True)
    try:
        r.reset()
        f.init(r)
        yr = f.run(r, True)
        if not _same(yr, y_true):
            dep.append(f"{fn}Reset: the standard says reset returns the instance to its state after instantiation; the "
                       f"same steps then gave {_show(yr, f.outs)} instead of {_show(y_true, f.outs)}")
            out["workarounds"]["no_reset"] = True
    except Exception as exc:
        dep.append(f"{fn}Reset: the standard says reset is allowed after steps; the FMU failed ({_failed(exc)})")
        out["workarounds"]["no_reset"] = True
    f.free(r)
    # directional derivatives at a communication point
    if f.flag("providesDirectionalDerivative") or f.flag("providesDirectionalDerivatives"):
        reals = [v for v in f.outs if v.type in REAL]
        if reals and f.ins:
            ran("derivatives")
            d = f.new()
            f.init(d)
            setr = d.setFloat64 if f.fmi3 else d.setReal
            getr = d.getFloat64 if f.fmi3 else d.getReal
            ovr = [v.valueReference for v in reals]
            try:
                for i, u in enumerate(f.ins):  # a generic point near the start values (no removable singularity)
                    x = getr([u.valueReference])[0]
                    setr([u.valueReference], [x + 0.01 * (1.0 + abs(x)) * (i + 1) / len(f.ins)])
                for u in f.ins:
                    x = getr([u.valueReference])[0]
                    jac = list(d.getDirectionalDerivative(ovr, [u.valueReference], [1.0]))
                    fds = []
                    for dx in (1e-6 * (1.0 + abs(x)), 1e-4 * (1.0 + abs(x))):
                        setr([u.valueReference], [x + dx])
                        yp = getr(ovr)
                        setr([u.valueReference], [x - dx])
                        ym = getr(ovr)
                        fds.append([(p - m) / (2 * dx) for p, m in zip(yp, ym)])
                    setr([u.valueReference], [x])
                    for v, j, fd, fd2 in zip(reals, jac, *fds):
                        if abs(fd - fd2) > 1e-4 * (1.0 + abs(fd)):
                            continue  # finite differences themselves unsettled here (not smooth): no verdict
                        if abs(j - fd) > 1e-4 * (1.0 + abs(fd)):
                            dep.append(f"{fn}GetDirectionalDerivative: the standard says it gives the partial "
                                       f"derivative at the current instant; d {v.name} / d {u.name} = {j:.6g}, finite "
                                       f"differences {fd:.6g}")
            except Exception as exc:
                dep.append(f"{fn}GetDirectionalDerivative: the FMU declares providesDirectionalDerivative; the call "
                           f"failed ({_failed(exc)})")
            f.free(d)
        else:
            out["skipped"]["derivatives"] = "no real inputs or outputs"
    else:
        out["skipped"]["derivatives"] = "providesDirectionalDerivative is false"
    # setters of every type
    ran("setters")
    w = f.new()
    tried = set()
    for v in f.vars:
        if v.causality not in ("parameter", "input") or v.variability == "constant" or v.start is None \
                or getattr(v, "dimensions", None) or v.type in tried:
            continue
        setter = {"Real": "setReal", "Float64": "setFloat64", "Integer": "setInteger", "Int32": "setInt32",
                  "Boolean": "setBoolean", "String": "setString", "Enumeration": "setInteger"}.get(v.type)
        if setter is None or (f.fmi3 and v.type == "Enumeration"):
            continue
        tried.add(v.type)
        raw = v.start
        value = (float(raw) if v.type in REAL else raw if v.type == "String" else
                 (str(raw).lower() in ("true", "1")) if v.type == "Boolean" else int(raw))
        try:
            getattr(w, setter)([v.valueReference], [value])
        except Exception as exc:
            dep.append(f"{fn}Set{setter[3:]}: the standard says a {v.causality} may be set to its start value before initialisation; "
                         f"{v.name} = {raw!r} failed ({_failed(exc)})")
    f.free(w)
    # a value set before initialisation must still be there after it
    reals = [v for v in f.vars if v.causality == "parameter" and v.type in REAL and v.variability in
             ("fixed", "tunable") and _float_start(v) is not None and not getattr(v, "dimensions", None)]
    if reals:
        v = reals[0]
        w = f.new()
        value = _float_start(v) + 1.0 + abs(_float_start(v))
        setr, getr = (w.setFloat64, w.getFloat64) if f.fmi3 else (w.setReal, w.getReal)
        try:
            setr([v.valueReference], [value])
            f.init(w)
            back = getr([v.valueReference])[0]
            if back != value:
                dep.append(f"{fn}Set{'Float64' if f.fmi3 else 'Real'}: the standard says a parameter set after "
                           f"instantiation keeps its value through initialisation; {v.name} set to {value:g} before "
                           f"initialisation read {back:g} after it")
                out["workarounds"]["set_in_init"] = True
        except Exception as exc:
            dep.append(f"{fn}Set{'Float64' if f.fmi3 else 'Real'}: the standard says a parameter may be set after "
                       f"instantiation; {v.name} = {value:g} failed ({_failed(exc)})")
        f.free(w)
    # communication points up to exactly the stop time
    ran("stop_time")
    z = f.new()
    stop = f.t0 + 2 * STEPS * f.h
    f.init(z, stop)
    k = 0
    try:
        if f.flag("canHandleVariableCommunicationStepSize"):
            for _ in range(2):
                z.doStep(f.t0 + k * f.h, f.h / 2, True)
                z.doStep(f.t0 + k * f.h + f.h / 2, f.h / 2, True)
                k += 1
        while k < 2 * STEPS:
            t = f.t0 + k * f.h
            z.doStep(t, (stop - t) if k == 2 * STEPS - 1 else f.h, True)  # the last step ends at stop exactly
            k += 1
    except Exception as exc:
        dep.append(f"{fn}DoStep: the standard says steps up to the stop time {stop:g} s (given at initialisation) are "
                   f"allowed; the step from {f.t0 + k * f.h:.9g} s failed ({_failed(exc)})")
    f.free(z)
    return out


def check_in_subprocess(path: Path, timeout: float = 120.0) -> dict:
    """:func:`check` in a child process (banners on stdout, crashes and hangs stay there)."""

    try:
        res = subprocess.run([sys.executable, "-m", "cosim.slaves.behaviour", str(path)], capture_output=True,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise UserError(f"{Path(path).name}: the behavioural check did not finish in {timeout:g} s") from None
    marker = "@@behaviour@@"
    line = next((x for x in res.stdout.splitlines()[::-1] if x.startswith(marker)), None)
    if line is None:
        tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
        raise UserError(f"{Path(path).name}: the behavioural check crashed (exit code {res.returncode}: {tail})")
    return json.loads(line[len(marker):])


def main(argv: list[str]) -> int:
    try:
        result = check(Path(argv[0]))
    except Exception as exc:  # an FMU that fails before any check could run
        result = {"departures": [f"the FMU could not be instantiated and initialised ({_failed(exc)})"],
                  "workarounds": {"always_no_prior": False, "no_rollback": False, "no_reset": False, "set_in_init": False}, "checks": [], "skipped": {}}
    sys.stdout.flush()
    print("@@behaviour@@" + json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
