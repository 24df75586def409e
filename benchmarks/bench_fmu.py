"""FMU exporter benchmark: build time per block, and the cost of one ``doStep``.

For every block of the model catalog (``models.blocks``, when installed) and a few reference
blocks (a mass-spring-damper, the thesis's stiff parasitic joint, a sampled lag), this script

1. builds the FMI 2.0 FMU into an empty cache (cold build: C generation + compile + pack) and
   again (warm: cache hit), against the targets "every thesis block < 5 s, multibody < 30 s";
2. times one communication step -- set the first input (a 5 Hz sine), ``doStep`` with h = 1 ms
   or the sample period -- three ways:
   - ``fmpy``: FMPy's ``FMU2Slave.doStep`` from a Python loop (what a Python master pays),
   - ``ctypes``: the raw ``fmi2DoStep`` symbol called through ctypes (the floor for Python),
   - ``C``: a C driver that dlopens the same shared library and loops ``fmi2DoStep``
     (the generated code alone, the peer the Python figures are compared with).

Usage: ``python3 benchmarks/bench_fmu.py [--steps N] [--fmi 2|3] [--only NAME ...]``
"""
from __future__ import annotations

import argparse
import ctypes
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi as ca
import fmpy
from fmpy.fmi2 import FMU2Slave

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import fmus  # noqa: E402
from models.block import Block, Param, Var  # noqa: E402

DRIVER = r"""
#include <dlfcn.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
typedef void *(*inst_t)(const char *, int, const char *, const char *, const void *, int, int);
typedef int (*fn0_t)(void *);
typedef int (*setup_t)(void *, int, double, double, int, double);
typedef int (*step_t)(void *, double, double, int);
typedef void (*free_t)(void *);
typedef int (*setr_t)(void *, const unsigned int *, size_t, const double *);
static void logger(void *env, const char *n, int s, const char *c, const char *m, ...) {
    (void)env; (void)n; (void)s; (void)c; fprintf(stderr, "%s\n", m);
}
struct cb { void *logger, *alloc, *free, *finished, *env; };
int main(int argc, char **argv) {
    void *lib = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
    const char *guid = argv[2];
    double h = atof(argv[3]);
    long n = atol(argv[4]), k;
    int vr_in = atoi(argv[5]);
    unsigned int vr = (unsigned int)(vr_in < 0 ? 0 : vr_in);
    double amp = atof(argv[6]), u;
    struct cb cbs = {(void *)logger, (void *)calloc, (void *)free, 0, 0};
    struct timespec t0, t1;
    void *c;
    if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 1; }
    c = ((inst_t)dlsym(lib, "fmi2Instantiate"))("bench", 1, guid, "", &cbs, 0, 0);
    if (!c) return 2;
    ((setup_t)dlsym(lib, "fmi2SetupExperiment"))(c, 0, 0.0, 0.0, 0, 0.0);
    ((fn0_t)dlsym(lib, "fmi2EnterInitializationMode"))(c);
    ((fn0_t)dlsym(lib, "fmi2ExitInitializationMode"))(c);
    step_t step = (step_t)dlsym(lib, "fmi2DoStep");
    setr_t set = (setr_t)dlsym(lib, "fmi2SetReal");
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (k = 0; k < n; ++k) {
        if (vr_in >= 0) { u = amp * sin(31.41592653589793 * k * h); set(c, &vr, 1, &u); }
        if (step(c, k * h, h, 1) > 1) { fprintf(stderr, "doStep failed at step %ld\n", k); return 3; }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    printf("%.6f\n", ((t1.tv_sec - t0.tv_sec) * 1e9 + (t1.tv_nsec - t0.tv_nsec)) / n / 1e3);
    ((free_t)dlsym(lib, "fmi2FreeInstance"))(c);
    return 0;
}
"""


# --- reference blocks -----------------------------------------------------------------------
def _msd(name: str, m: float, k: float, c: float, integrator: str, substeps: int) -> Block:
    p, x, u = ca.SX.sym("p", 3), ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    acc = (u[0] - p[1] * x[0] - p[2] * x[1]) / p[0]
    return Block.build(name, description="mass-spring-damper",
                       params=[Param("m", m, "kg", 1e-9), Param("k", k, "N/m", 0.0), Param("c", c, "N.s/m", 0.0)],
                       inputs=[Var("f", "N")], outputs=[Var("s", "m"), Var("v", "m/s")],
                       states=[Var("x.s", "m"), Var("x.v", "m/s")], p=p, u=u, x=x,
                       ode=ca.vertcat(x[1], acc), out=x, start=ca.DM([1e-3, 0.0]),
                       integrator=integrator, substeps=substeps)


def _lag() -> Block:
    p, x, u = ca.SX.sym("p", 1), ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    a = ca.exp(-1e-3 / p[0])
    return Block.build("ref_lag", description="sampled lag", params=[Param("T", 0.05, "s", 1e-6)],
                       inputs=[Var("u")], outputs=[Var("y")], states=[Var("x")], p=p, u=u, x=x,
                       ode=a * x + (1 - a) * u, out=x, start=ca.DM([0.0]), integrator="discrete",
                       sample_period=1e-3)


def _chain(nb: int = 7) -> Block:
    """``nb`` planar rigid bodies (0.3 m, 1 kg, 0.03 kg m2) in a chain, joined end to end by
    stiff spring-dampers (1e8 N/m, 2000 N s/m): a stand-in of the multibody mechanism's size
    (6 nb states) and stiffness."""
    x, u, p = ca.SX.sym("x", 6 * nb), ca.SX.sym("u", 3), ca.SX.sym("p", 4)
    k, c, m, inertia = p[0], p[1], p[2], p[3]
    half = 0.15
    wrench = [[0, 0, 0] for _ in range(nb)]
    for i in range(nb - 1):
        a, b = x[6 * i:6 * i + 6], x[6 * i + 6:6 * i + 12]
        ra = half * ca.vertcat(ca.cos(a[2]), ca.sin(a[2]))
        rb = -half * ca.vertcat(ca.cos(b[2]), ca.sin(b[2]))
        va = a[3:5] + a[5] * ca.vertcat(-ra[1], ra[0])
        vb = b[3:5] + b[5] * ca.vertcat(-rb[1], rb[0])
        f = k * (b[0:2] + rb - a[0:2] - ra) + c * (vb - va)
        for j, (r, sgn) in ((i, (ra, 1)), (i + 1, (rb, -1))):
            wrench[j] = [wrench[j][0] + sgn * f[0], wrench[j][1] + sgn * f[1],
                         wrench[j][2] + sgn * (r[0] * f[1] - r[1] * f[0])]
    wrench[0][0] += u[0]
    wrench[0][1] += u[1]
    wrench[-1][2] += u[2]
    ode = []
    for i in range(nb):
        ode += [x[6 * i + 3], x[6 * i + 4], x[6 * i + 5], wrench[i][0] / m, wrench[i][1] / m, wrench[i][2] / inertia]
    start = []
    for i in range(nb):
        start += [2 * half * i, 0.0, 0.0, 0.0, 0.0, 0.0]
    states = [Var(f"body[{i + 1}].{q}") for i in range(nb) for q in ("x", "y", "phi", "vx", "vy", "omega")]
    return Block.build("ref_chain", description="stiff chain of planar bodies",
                       params=[Param("k", 1e8, "N/m", 0.0), Param("c", 2000.0, "N.s/m", 0.0),
                               Param("m", 1.0, "kg", 1e-9), Param("I", 0.03, "kg.m2", 1e-12)],
                       inputs=[Var("fx", "N"), Var("fy", "N"), Var("tz", "N.m")],
                       outputs=[Var(f"position[{i + 1}].x", "m") for i in range(nb)],
                       states=states,
                       p=p, u=u, x=x, ode=ca.vertcat(*ode), out=ca.vertcat(*[x[6 * i] for i in range(nb)]),
                       start=ca.DM(start), integrator="radau")


def reference_blocks() -> list[tuple[str, Block, float]]:
    """(label, block, build-time target [s])."""
    return [("ref msd rk4 x4", _msd("ref_msd", 1.0, 100.0, 2.0, "rk4", 4), 5.0),
            ("ref stiff joint radau", _msd("ref_stiff", 1.0, 1e8, 2000.0, "radau", 1), 5.0),
            ("ref lag discrete", _lag(), 5.0),
            ("ref 7-body stiff chain", _chain(), 30.0)]


def catalog_blocks() -> list[tuple[str, Block, float]]:
    try:
        import models.blocks as blocks
    except ModuleNotFoundError as exc:
        if exc.name != "models.blocks":
            raise
        print("models.blocks is not installed: reference blocks only", file=sys.stderr)
        return []
    out = []
    for model, fidelities in blocks.catalog().items():
        for fid in fidelities:
            target = 30.0 if (model, fid) == ("mechanism", "multibody") else 5.0
            out.append((f"{model} {fid}", blocks.make(model, fid), target))
    return out


# --- timing ---------------------------------------------------------------------------------
def _input(blk: Block) -> tuple[int, float]:
    """Value reference and amplitude of the sinusoidal input driven each step (-1: none).
    Value references: 0 time, then parameters, states, inputs (fmus.model_description)."""
    if not blk.inputs:
        return -1, 0.0
    return 1 + len(blk.params) + len(blk.states), 1.0


def time_fmpy(path: Path, h: float, n: int, vr: int, amp: float) -> tuple[float, float]:
    """µs per (set input, doStep) via FMPy's FMU2Slave and via the raw ctypes symbols."""
    md = fmpy.read_model_description(str(path))
    unz = fmpy.extract(str(path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unz, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="bench")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    w = 10 * math.pi
    do_step, set_real = fmu.doStep, fmu.setReal
    vrs = [vr]
    t0 = time.perf_counter()
    for k in range(n):
        if vr >= 0:
            set_real(vrs, [amp * math.sin(w * k * h)])
        do_step(k * h, h)
    t_fmpy = (time.perf_counter() - t0) / n * 1e6
    raw = fmu.dll.fmi2DoStep
    raw.argtypes = [ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_int]
    raw.restype = ctypes.c_int
    raw_set = fmu.dll.fmi2SetReal
    raw_set.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint), ctypes.c_size_t,
                        ctypes.POINTER(ctypes.c_double)]
    raw_set.restype = ctypes.c_int
    vr_c, u_c = (ctypes.c_uint * 1)(max(vr, 0)), (ctypes.c_double * 1)()
    comp = fmu.component
    t_end = n * h
    t0 = time.perf_counter()
    for k in range(n):
        if vr >= 0:
            u_c[0] = amp * math.sin(w * k * h)
            raw_set(comp, vr_c, 1, u_c)
        raw(comp, t_end + k * h, h, 1)
    t_ctypes = (time.perf_counter() - t0) / n * 1e6
    fmu.terminate()
    fmu.freeInstance()
    return t_fmpy, t_ctypes


def time_c(path: Path, driver: Path, h: float, n: int, vr: int, amp: float) -> float:
    """µs per (set input, doStep) from the C driver (same shared library, no Python)."""
    md = fmpy.read_model_description(str(path))
    unz = fmpy.extract(str(path))
    lib = next(Path(unz, "binaries").rglob("*.so"))
    res = subprocess.run([str(driver), str(lib), md.guid, repr(h), str(n), str(vr), repr(amp)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        print(f"  C driver failed: {res.stderr.strip()}", file=sys.stderr)
        return math.nan
    return float(res.stdout.strip())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000, help="doStep calls per timing (default 20000)")
    ap.add_argument("--only", nargs="*", help="labels (substrings) to run")
    args = ap.parse_args(argv)
    cases = catalog_blocks() + reference_blocks()
    if args.only:
        cases = [c for c in cases if any(s in c[0] for s in args.only)]
    work = Path(tempfile.mkdtemp(prefix="bench-fmu-"))
    driver = work / "driver"
    (work / "driver.c").write_text(DRIVER)
    subprocess.run(["gcc", "-O2", str(work / "driver.c"), "-o", str(driver), "-ldl", "-lm"], check=True)
    head = (f"{'block':<26} {'int':>8} {'nx':>3} {'cold s':>7} {'target':>6} {'warm s':>7} "
            f"{'fmpy us':>8} {'ctypes us':>9} {'C us':>7} {'fmpy/C':>7}")
    rows = [head, "-" * len(head)]
    for label, blk, target in cases:
        cache = work / "cache"
        t0 = time.perf_counter()
        path = fmus.build_fmu(blk, cache_dir=cache, progress=lambda m: print(f"  {m}", file=sys.stderr))
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        fmus.build_fmu(blk, cache_dir=cache, progress=lambda m: None)
        warm = time.perf_counter() - t0
        h = float(blk.sample_period) if blk.integrator == "discrete" else 1e-3
        n = args.steps
        vr, amp = _input(blk)
        t_fmpy, t_ctypes = time_fmpy(path, h, n, vr, amp)
        t_c = time_c(path, driver, h, n, vr, amp)
        flag = "ok" if cold < target else "OVER"
        rows.append(f"{label:<26} {blk.integrator:>8} {len(blk.states):>3} {cold:>7.2f} {target:>4.0f}{flag:>3}"
                    f"{warm:>7.3f} {t_fmpy:>8.2f} {t_ctypes:>9.2f} {t_c:>7.3f} {t_fmpy / t_c:>7.1f}")
        print(rows[-1], file=sys.stderr)
    print("\n".join(rows))
    print(f"(per step: set the first input to a 5 Hz sine, then doStep with h = 1 ms or the sample period; "
          f"{args.steps} steps; C = a C driver dlopening the same library; cold = empty cache, warm = cache hit)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
