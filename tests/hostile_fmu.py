"""A hostile FMI 2.0 co-simulation FMU, compiled from a few lines of C at test time: a first-order
lag ``y' = (u - y) / tau`` (explicit Euler) that misbehaves in one chosen FMI call.

``RPR_HOSTILE=<call>:<action>`` in the environment of the process that loads it picks the
misbehaviour: call ``instantiate``, ``doStep`` (also ``doStep@N``, the N-th doStep) or
``enterInit``; action ``segv`` (a NULL write), ``abort``, ``exit0`` (``exit(0)``), ``sigkill``
(``raise(SIGKILL)``: as if the OOM killer struck), ``hang``
(a busy loop), ``sleep`` (``sleep(3600)``) or ``hang_noterm`` (SIGTERM ignored, then a busy loop);
a suffix ``/TAU`` (e.g. ``doStep@5:segv/0.2``) restricts it to the instance whose parameter
``tau`` is TAU (one run of a batch).
Without it the FMU behaves.
"""
from __future__ import annotations

import subprocess
import zipfile
from pathlib import Path

C_SOURCE = r"""
#include <signal.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
typedef void *fmi2Component;
typedef struct { double u, y, tau; long steps; } inst_t;
static void misbehave(const char *call, long n, double tau) {
    const char *spec = getenv("RPR_HOSTILE");
    char want[64], act[64];
    const char *colon, *at, *slash;
    long nth = 1;
    size_t len;
    if (!spec || !(colon = strchr(spec, ':'))) return;
    if ((slash = strchr(colon, '/')) && (tau < 0 || atof(slash + 1) != tau)) return;
    len = (size_t)(colon - spec);
    if (len >= sizeof want) return;
    memcpy(want, spec, len); want[len] = 0;
    if ((at = strchr(want, '@'))) { nth = atol(at + 1); want[at - want] = 0; }
    if (strcmp(want, call) || n != nth) return;
    colon++;
    len = slash ? (size_t)(slash - colon) : strlen(colon);
    if (len >= sizeof act) return;
    memcpy(act, colon, len); act[len] = 0;
    colon = act;
    if (!strcmp(colon, "segv")) { volatile int *p = 0; *p = 1; }
    if (!strcmp(colon, "abort")) abort();
    if (!strcmp(colon, "exit0")) exit(0);
    if (!strcmp(colon, "sigkill")) raise(SIGKILL);
    if (!strcmp(colon, "sleep")) sleep(3600);
    if (!strcmp(colon, "hang_noterm")) { signal(SIGTERM, SIG_IGN); signal(SIGINT, SIG_IGN); }
    if (!strcmp(colon, "hang") || !strcmp(colon, "hang_noterm")) for (;;) { }
}
const char *fmi2GetTypesPlatform(void) { return "default"; }
const char *fmi2GetVersion(void) { return "2.0"; }
int fmi2SetDebugLogging(void *c, int on, size_t n, const char *cats[]) { return 0; }
fmi2Component fmi2Instantiate(const char *name, int type, const char *guid, const char *loc, const void *cb,
                              int vis, int log) {
    inst_t *s;
    misbehave("instantiate", 1, -1);
    s = calloc(1, sizeof *s);
    s->tau = 0.1;
    return s;
}
void fmi2FreeInstance(void *c) { free(c); }
int fmi2SetupExperiment(void *c, int tol_def, double tol, double t0, int stop_def, double t1) { return 0; }
int fmi2EnterInitializationMode(void *c) { misbehave("enterInit", 1, ((inst_t *)c)->tau); return 0; }
int fmi2ExitInitializationMode(void *c) { return 0; }
int fmi2Terminate(void *c) { return 0; }
int fmi2Reset(void *c) { inst_t *s = c; s->u = s->y = 0; s->tau = 0.1; s->steps = 0; return 0; }
int fmi2GetReal(void *c, const unsigned *vr, size_t n, double *v) {
    inst_t *s = c; size_t i;
    for (i = 0; i < n; ++i) v[i] = vr[i] == 0 ? s->u : vr[i] == 1 ? s->y : s->tau;
    return 0;
}
int fmi2SetReal(void *c, const unsigned *vr, size_t n, const double *v) {
    inst_t *s = c; size_t i;
    for (i = 0; i < n; ++i) { if (vr[i] == 0) s->u = v[i]; else if (vr[i] == 2) s->tau = v[i]; }
    return 0;
}
int fmi2GetInteger(void *c, const unsigned *vr, size_t n, int *v) { return 0; }
int fmi2SetInteger(void *c, const unsigned *vr, size_t n, const int *v) { return 0; }
int fmi2GetBoolean(void *c, const unsigned *vr, size_t n, int *v) { return 0; }
int fmi2SetBoolean(void *c, const unsigned *vr, size_t n, const int *v) { return 0; }
int fmi2GetString(void *c, const unsigned *vr, size_t n, const char **v) { return 0; }
int fmi2SetString(void *c, const unsigned *vr, size_t n, const char *const *v) { return 0; }
int fmi2DoStep(void *c, double t, double h, int no_prior) {
    inst_t *s = c;
    misbehave("doStep", ++s->steps, s->tau);
    s->y += h * (s->u - s->y) / s->tau;
    return 0;
}
int fmi2CancelStep(void *c) { return 0; }
int fmi2GetStatus(void *c, int k, int *v) { return 3; }
int fmi2GetRealStatus(void *c, int k, double *v) { return 3; }
int fmi2GetIntegerStatus(void *c, int k, int *v) { return 3; }
int fmi2GetBooleanStatus(void *c, int k, int *v) { return 3; }
int fmi2GetStringStatus(void *c, int k, const char **v) { return 3; }
int fmi2SetRealInputDerivatives(void *c, const unsigned *vr, size_t n, const int *o, const double *v) { return 0; }
int fmi2GetRealOutputDerivatives(void *c, const unsigned *vr, size_t n, const int *o, double *v) { return 0; }
int fmi2GetFMUstate(void *c, void **st) { return 3; }
int fmi2SetFMUstate(void *c, void *st) { return 3; }
int fmi2FreeFMUstate(void *c, void **st) { return 3; }
int fmi2SerializedFMUstateSize(void *c, void *st, size_t *n) { return 3; }
int fmi2SerializeFMUstate(void *c, void *st, char *b, size_t n) { return 3; }
int fmi2DeSerializeFMUstate(void *c, const char *b, size_t n, void **st) { return 3; }
int fmi2GetDirectionalDerivative(void *c, const unsigned *a, size_t na, const unsigned *b, size_t nb,
                                 const double *dv, double *out) { return 3; }
"""

MODEL_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="hostile" guid="{hostile-0001}" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="hostile" canHandleVariableCommunicationStepSize="true"/>
  <DefaultExperiment startTime="0" stopTime="1" stepSize="0.001"/>
  <ModelVariables>
    <ScalarVariable name="u" valueReference="0" causality="input" variability="continuous"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="y" valueReference="1" causality="output" variability="continuous" initial="exact"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="tau" valueReference="2" causality="parameter" variability="fixed"><Real start="0.1"/></ScalarVariable>
  </ModelVariables>
  <ModelStructure><Outputs><Unknown index="2"/></Outputs></ModelStructure>
</fmiModelDescription>
"""


def build_hostile_fmu(folder: Path) -> Path:
    """``folder/hostile.fmu`` (compiled with the system C compiler)."""
    folder.mkdir(parents=True, exist_ok=True)
    src = folder / "hostile.c"
    src.write_text(C_SOURCE)
    lib = folder / "hostile.so"
    subprocess.run(["gcc", "-O1", "-shared", "-fPIC", "-o", str(lib), str(src)], check=True)
    fmu = folder / "hostile.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.writestr("modelDescription.xml", MODEL_DESCRIPTION)
        z.write(lib, "binaries/linux64/hostile.so")
    return fmu


def hostile_scene(folder: Path, fmu: Path, *, stop_time: float = 0.5, name: str = "hostile") -> Path:
    """A scene of two copies of the hostile FMU, ``a.y -> b.u`` (so that the compiled loop sets
    and gets values every step), ``a`` driven by its start input 1."""
    path = folder / f"{name}.yaml"
    path.write_text(f"name: {name}\nstop_time: {stop_time}\n"
                    f"components:\n  a: {{fmu: {fmu}, start: {{u: 1.0}}}}\n  b: {{fmu: {fmu}}}\n"
                    f"connections:\n  - a.y -> b.u\n"
                    f"master: {{algorithm: gauss_seidel, step: 1e-3, estimate: false}}\n"  # no companion run first
                    f"outputs: [a.y, b.y]\n")
    return path
