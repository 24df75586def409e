"""A small FMI 2.0 co-simulation FMU in C, built with one chosen defect (for the behavioural
check's tests) or none: x' = k (u - x) + 1 by forward Euler, output y = x + G u (G = 2 with
``feedthrough``, else 0); parameters of every type (Real k, Integer n, Boolean b, String s).
Its ModelStructure lists no output dependencies unless ``declare`` is given."""
from __future__ import annotations

import shutil
import subprocess
import zipfile
from pathlib import Path

DEFECTS = ("none", "no_advance_false", "bad_restore", "reused_pointer", "shared_instances", "nondeterministic",
           "bad_reset", "bad_derivative", "setter_fails", "strict_stop", "forgets_parameters")

SOURCE = r"""
#include <stdlib.h>
#include <string.h>
#include "fmi2Functions.h"
typedef struct { double k, u, x, t, stop; int n, b, has_stop; } S;
static S shared_s;
static unsigned long calls = 0;
#ifndef G
#define G 0.0
#endif
static void reset_s(S *s) { s->k = 1.0; s->u = 0.5; s->x = 0.0; s->t = 0.0; s->n = 3; s->b = 1; s->has_stop = 0; }
const char *fmi2GetTypesPlatform(void) { return "default"; }
const char *fmi2GetVersion(void) { return "2.0"; }
fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean l, size_t n, const fmi2String x[]) { return fmi2OK; }
fmi2Component fmi2Instantiate(fmi2String n, fmi2Type t, fmi2String g, fmi2String r, const fmi2CallbackFunctions *f,
                              fmi2Boolean v, fmi2Boolean l) {
#ifdef SHARED_INSTANCES
    S *s = &shared_s;
#else
    S *s = calloc(1, sizeof(S));
#endif
    reset_s(s); return s;
}
void fmi2FreeInstance(fmi2Component c) {
#ifndef SHARED_INSTANCES
    free(c);
#endif
}
fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean td, fmi2Real tol, fmi2Real t0, fmi2Boolean sd, fmi2Real stop) {
    S *s = c; s->t = t0; s->has_stop = sd; s->stop = stop;
#ifdef FORGETS_PARAMETERS
    s->k = 1.0;
#endif
    return fmi2OK; }
fmi2Status fmi2EnterInitializationMode(fmi2Component c) { return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) {
#ifdef BAD_RESET
    return fmi2OK;
#else
    reset_s(c); return fmi2OK;
#endif
}
fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real v[]) {
    S *s = c; size_t i;
    for (i = 0; i < nvr; i++) v[i] = vr[i] == 0 ? s->k : vr[i] == 1 ? s->u : s->x + G * s->u;
    return fmi2OK;
}
fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real v[]) {
    S *s = c; size_t i;
    for (i = 0; i < nvr; i++) { if (vr[i] == 0) s->k = v[i]; else if (vr[i] == 1) s->u = v[i]; else return fmi2Error; }
    return fmi2OK;
}
fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer v[]) {
    size_t i; for (i = 0; i < nvr; i++) v[i] = ((S *)c)->n; return fmi2OK; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer v[]) {
#ifdef SETTER_FAILS
    return fmi2Error;
#else
    size_t i; for (i = 0; i < nvr; i++) ((S *)c)->n = v[i]; return fmi2OK;
#endif
}
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean v[]) {
    size_t i; for (i = 0; i < nvr; i++) v[i] = ((S *)c)->b; return fmi2OK; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean v[]) {
    size_t i; for (i = 0; i < nvr; i++) ((S *)c)->b = v[i]; return fmi2OK; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String v[]) {
    size_t i; for (i = 0; i < nvr; i++) v[i] = "x"; return fmi2OK; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String v[]) { return fmi2OK; }
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *st) {
#ifdef REUSED_POINTER
    if (*st) return fmi2OK;
#endif
    if (!*st) *st = malloc(sizeof(S));
    memcpy(*st, c, sizeof(S)); return fmi2OK;
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate st) {
#ifndef BAD_RESTORE
    memcpy(c, st, sizeof(S));
#endif
    return fmi2OK;
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *st) { free(*st); *st = NULL; return fmi2OK; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate st, size_t *n) { return fmi2Error; }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate st, fmi2Byte b[], size_t n) { return fmi2Error; }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *st) { return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dz[], fmi2Real du[]) {
    size_t i, j;
    for (i = 0; i < nu; i++) { du[i] = 0; for (j = 0; j < nz; j++) if (z[j] == 1 && u[i] == 2) du[i] += dz[j] * (G
#ifdef BAD_DERIVATIVE
        + 1.0
#endif
        ); }
    return fmi2OK;
}
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer o[], const fmi2Real v[]) { return fmi2Error; }
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer o[], fmi2Real v[]) { return fmi2Error; }
fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSet) {
    S *s = c;
#ifdef STRICT_STOP
    if (s->has_stop && t + h >= s->stop) return fmi2Error;
#endif
#ifdef NO_ADVANCE_FALSE
    if (!noSet) return fmi2OK;
#endif
    s->x += h * (s->k * (s->u - s->x) + 1.0);
#ifdef NONDETERMINISTIC
    s->x += 1e-9 * (double)(++calls);
#endif
    s->t = t + h; return fmi2OK;
}
fmi2Status fmi2CancelStep(fmi2Component c) { return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v) { return fmi2Error; }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v) { return fmi2Error; }
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v) { return fmi2Error; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v) { return fmi2Error; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v) { return fmi2Error; }
"""

MODEL = """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="{name}" guid="{{0b0e9a3c-7d1e-4b8a-9c55-{guid}}}" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="{name}" canHandleVariableCommunicationStepSize="true" canGetAndSetFMUstate="true"
                providesDirectionalDerivative="true"/>
  <DefaultExperiment startTime="0" stopTime="1" stepSize="{step}"/>
  <ModelVariables>
    <ScalarVariable name="k" valueReference="0" causality="parameter" variability="tunable"><Real start="1"/></ScalarVariable>
    <ScalarVariable name="u" valueReference="1" causality="input"><Real start="0.5"/></ScalarVariable>
    <ScalarVariable name="y" valueReference="2" causality="output"><Real/></ScalarVariable>
    <ScalarVariable name="n" valueReference="0" causality="parameter" variability="tunable"><Integer start="3"/></ScalarVariable>
    <ScalarVariable name="b" valueReference="0" causality="parameter" variability="tunable"><Boolean start="true"/></ScalarVariable>
    <ScalarVariable name="s" valueReference="0" causality="parameter" variability="tunable"><String start="x"/></ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs><Unknown index="3"{deps}/></Outputs>
  </ModelStructure>
</fmiModelDescription>
"""


def build(dest: Path, defect: str = "none", *, feedthrough: bool = False, declare: str | None = None,
          step: str = "0.01", name: str | None = None) -> Path:
    """Compile the FMU with ``defect`` into ``dest``/<name>.fmu and return its path.  ``declare``:
    the output's ``dependencies`` attribute as written (None: not written)."""
    assert defect in DEFECTS, defect
    import fmpy

    name = name or f"t_{defect}{'_ft' if feedthrough else ''}{'' if declare is None else '_decl'}"
    work = dest / f"{name}.build"
    work.mkdir(parents=True, exist_ok=True)
    (work / "model.c").write_text(SOURCE)
    so = work / f"{name}.so"
    flags = [] if defect == "none" else [f"-D{defect.upper()}"]
    if feedthrough:
        flags.append("-DG=2.0")
    cc = shutil.which("gcc") or shutil.which("cc")
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(so), str(work / "model.c"),
                    f"-I{Path(fmpy.__file__).parent / 'c-code'}", *flags], check=True, capture_output=True)
    guid = format(abs(hash(name)) % (1 << 48), "012x")
    deps = "" if declare is None else f' dependencies="{declare}"'
    fmu = dest / f"{name}.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.writestr("modelDescription.xml", MODEL.format(name=name, guid=guid, deps=deps, step=step))
        z.write(so, f"binaries/linux64/{name}.so")
    return fmu
