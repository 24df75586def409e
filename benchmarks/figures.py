"""The accuracy figures of the documentation's results pages, measured and printed.

The tests assert these numbers against their independent sources (the thesis's tables as
restated in SPEC.md, a Lagrange formulation, the virtual-work reference); this script prints
the values themselves, so every figure the README quotes comes from a command.  It reuses the
tests' helpers (the Lagrange formulation, the virtual-work error measure) rather than writing
those equations a second time.

    python benchmarks/figures.py            # models: thesis tables (Ch. 4-7), Lagrange, stiffness series (~30 s)
    python benchmarks/figures.py --scenes   # also the scenes: pid_step, multibody, vw_compare (~2 min)
    python benchmarks/figures.py --only kinematics   # Table 6.12, Chapter 7, virtual work vs Lagrange (~2 s)
    python benchmarks/figures.py --check [PAGE.md ...]   # pages' quoted outputs against what the commands print

``--check`` finds, in the documentation's pages (default: every ``docs/**/*.md``), each fenced
block whose first line is ``$ COMMAND`` (the command's printed output quoted below it, whole or
in part, with a line saying when and where it was printed just above the block), runs the cheap
commands (:data:`CHEAP`: this script's kinematics section, the quick start's run against the
monolithic reference) and reports every quoted line that the command no longer prints; exit code
1 when one differs.  Blocks of expensive commands are listed as not checked.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from docgen.quoted import drifted, quoted_blocks  # noqa: E402

TUTORIAL = (ROOT / "docs" / "tutorial.md").resolve()

# SPEC §5 (thesis Tables 7.3-7.9, virtual-work column, matched instants) and the thesis's own bands
CHAPTER_7 = [("leg lengths (7.3)", "L", 0.2335, (0.309994594, 0.372398991, 0.276864985), "0.2 %"),
             ("leg rates (7.5)", "Ld", 0.234, (-0.162204534, -0.163456366, -0.017791517), "0.8 % (leg 3: 5 %)"),
             ("leg accelerations (7.7)", "Ldd", 0.5, (0.678478249, 0.696504281, 0.019889875), "0.2 % (leg 3: 2 %)")]
TABLE_7_9 = (2.610272368, 1.440588406, 0.693698204)
TABLE_6_12 = [((-0.15, -0.15, 0.0), (0.3109, 0.3559, 0.2043)), ((-0.2, -0.15, 0.2), (0.3415, 0.3641, 0.2613))]


def models_figures() -> None:
    kinematics_figures()
    chapter_4_figures()
    stiffness_series()


def kinematics_figures() -> None:
    """Table 6.12's leg lengths, Chapter 7's path and forces, virtual work against Lagrange."""
    from models import geometry as G
    from models import kinematics as K
    from models import virtual_work as V
    from test_kinematics import leg_motion, sine_path

    cross = G.preset("cross_leg")
    err = max(np.abs(K.ik(cross, pose)[0] - legs).max() for pose, legs in TABLE_6_12)
    print(f"Table 6.12 start and target leg lengths: max |error| {err:.1e} m (printed to four places)")
    print("Chapter 7 path against the thesis (relative error per leg; the thesis's own band):")
    for label, key, t, want, band in CHAPTER_7:
        got = leg_motion(*sine_path(t))[key].ravel()
        rel = np.abs(got / np.array(want) - 1)
        print(f"  {label:<24} t = {t:<6} " + " / ".join(f"{100 * r:.2f} %" for r in rel) + f"   (thesis: {band})")
    q, qd, qdd = sine_path(0.5)
    tau = V.inverse_dynamics(cross, q, qd, qdd)
    rel = np.abs(tau / np.array(TABLE_7_9) - 1)
    print(f"  {'forces (7.9)':<24} t = {0.5:<6} " + " / ".join(f"{100 * r:.2f} %" for r in rel)
          + "   (thesis: <= 1 %)   tau = " + " / ".join(f"{f:.4f}" for f in tau) + " N")
    from test_virtual_work import STATES, lagrange_forces

    worst = 0.0
    for q, qd, qdd in STATES:
        ref = np.array(lagrange_forces()(q, qd, qdd, cross.geometry_vector(), cross.inertia.vector())[0]).ravel()
        worst = max(worst, np.abs(V.inverse_dynamics(cross, q, qd, qdd) - ref).max() / np.abs(ref).max())
    print(f"virtual work against Lagrange's equations ({len(STATES)} random states): max relative "
          f"difference {worst:.1e}")


def chapter_4_figures() -> None:
    """Tables 4.5 and 4.9 against the thesis (the values themselves: ``rpr-cosim analyze --study all``)."""
    from models import analysis as A
    from models import geometry as G
    from test_analysis import RATIOS, TABLE_4_5, TABLE_4_9_HIGHEST_X, TABLE_4_9_HIGHEST_Y

    rows = {name: A.table_4_5_row(G.preset(name)) for name in ("config1", "config2", "config3", "config4")}
    for name, want in sorted(TABLE_4_5.items()):
        got = np.array([rows[name][c] for c in A.SUMMARY_COLUMNS])
        print(f"Table 4.5 {name}: max relative deviation over its 8 values {np.max(np.abs(got / want - 1)):.1e}")
    print("Table 4.5 overall DSI of the singular designs (numerical zero): "
          + ", ".join(f"{n} {rows[n]['mu_max']:.1e} (N = {rows[n].grid_n})" for n in ("config1", "config3")))
    study = {r.ratio: r.summary for r in A.platform_size_study(RATIOS)}
    for col, ref in (("mu_x_max", TABLE_4_9_HIGHEST_X), ("mu_y_max", TABLE_4_9_HIGHEST_Y)):
        dev = max(abs(study[r][col] / ref[i] - 1) for i, r in enumerate(RATIOS))
        print(f"Table 4.9 highest {col[3]} DSI over the 12 ratios: max relative deviation {100 * dev:.2f} %")
    print(f"Table 4.9 highest overall DSI at ratio 0.1: {study[0.1]['mu_max']:.4g} on a "
          f"{A.PLATFORM_STUDY_GRID}x{A.PLATFORM_STUDY_GRID} grid (thesis: 4.4563)")


def stiffness_series() -> None:
    """The multibody block against the rigid block (both CVODES at 1e-10) under constant leg
    forces for 0.2 s, as the parasitic joints stiffen (tests/test_blocks.py asserts the trend)."""
    import models.blocks as B
    from test_blocks import FORCE, simulate

    ts = np.linspace(0.0, 0.2, 21)
    rigid = simulate(B.make("mechanism", "rigid"), ts, u=FORCE)[0]
    print("multibody against rigid mechanism (constant leg forces, 0.2 s, CVODES): max |error|")
    for k in (1e6, 1e7, 1e8):
        ys = simulate(B.make("mechanism", "multibody", k_joint=k, k_rot=k), ts, u=FORCE, tol=1e-10)[0]
        print(f"  k = {k:.0e} N/m: pose {np.abs(ys[:, :3] - rigid[:, :3]).max():.1e}, "
              f"legs {np.abs(ys[:, 6:9] - rigid[:, 6:9]).max():.1e} m")


def scene_figures(cache: Path) -> None:
    from cosim.run.execute import run
    from test_scenes import (BAND_LEG, BAND_PHI, LEGS, SCENES, TARGET_POSE, THESIS_END_LEGS, THESIS_END_POSE,
                             leg_error, vw_errors)

    res = run(SCENES / "pid_step.yaml", ["stop_time=15"], cache_dir=cache)
    tr, t = res.trace, res.trace.time
    phi, x = tr["mech.platform.phi"], tr["mech.platform.x"]
    k = int(np.argmax(phi))
    print(f"pid_step (rigid, {res.stats['algorithm']}, {res.scene.master.step * 1e3:g} ms, "
          f"{res.scene.master.inputs} inputs): phi peaks at {phi[k]:.4f} rad at {t[k]:.2f} s; x dips to "
          f"{x.min():.4f} m at {t[np.argmin(x)]:.2f} s; L1 peaks at {tr['mech.leg[1].s'].max():.4f} m")
    legs5 = [abs(tr.at(f"mech.leg[{i}].s", 5.0) - THESIS_END_LEGS[i - 1]) for i in LEGS]
    print("  at 5 s, from Table 6.12's end state: legs " + " / ".join(f"{1e3 * d:.2f}" for d in legs5)
          + f" mm, phi {abs(tr.at('mech.platform.phi', 5.0) - THESIS_END_POSE[2]):.4f} rad "
          f"(the thesis's band: {BAND_LEG * 1e3:g} mm, {BAND_PHI:g} rad)")
    print("  at 5 s, from the target: legs " + " / ".join(
        f"{1e3 * abs(tr.at(f'mech.leg[{i}].s', 5.0) - tr.at(f'target.leg[{i}].s', 5.0)):.2f}" for i in LEGS)
        + f" mm, phi {abs(tr.at('mech.platform.phi', 5.0) - TARGET_POSE[2]):.4f} rad")
    out = (leg_error(tr) > BAND_LEG) | (np.abs(phi - TARGET_POSE[2]) > BAND_PHI)
    print(f"  enters the thesis's band for good at {t[np.nonzero(out)[0][-1] + 1]:.2f} s")
    rigid = run(SCENES / "pid_step.yaml", [], cache_dir=cache).trace
    mb = run(SCENES / "pid_step_multibody.yaml", [], cache_dir=cache).trace
    n = len(mb.time)
    diff = {v: np.abs(rigid[v][:n] - mb[v]).max() for v in
            [f"mech.leg[{i}].s" for i in LEGS] + ["mech.platform.x", "mech.platform.y", "mech.platform.phi"]}
    print("pid_step_multibody against pid_step over 5 s: legs " + " / ".join(
        f"{diff[f'mech.leg[{i}].s']:.1e}" for i in LEGS) + f" m, x {diff['mech.platform.x']:.1e} m, "
        f"y {diff['mech.platform.y']:.1e} m, phi {diff['mech.platform.phi']:.1e} rad")
    vw = run(SCENES / "vw_compare.yaml", ["master.algorithm=gauss_seidel"], cache_dir=cache)  # the models at 1 ms
    for mech in ("rigid", "multibody"):
        e = vw_errors(vw.trace, mech)
        print(f"vw_compare, {mech} against the virtual-work reference (relative to range): lengths {e['s']:.1e}, "
              f"rates {e['v']:.1e}, accelerations {e['a']:.1e}, forces {e['f']:.1e}")


#: Sections of this script by ``--only`` name.
SECTIONS = {"kinematics": kinematics_figures, "chapter4": chapter_4_figures, "stiffness": stiffness_series}
def _this_script(*args: str) -> Callable[[], list[str]]:
    def printed() -> list[str]:
        import contextlib
        import io

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            run(parse(list(args)))
        return buf.getvalue().splitlines()

    return printed


def _verb(*args: str) -> Callable[[], list[str]]:
    """``rpr-cosim ARGS`` in a subprocess, writing into a temporary ``--out``."""
    def printed() -> list[str]:
        import os
        import subprocess

        with tempfile.TemporaryDirectory() as out:
            env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
            res = subprocess.run([sys.executable, "-m", "cosim", *args, "--out", out], cwd=ROOT, env=env,
                                 capture_output=True, text=True, timeout=600)
        return res.stdout.splitlines()

    return printed


#: Commands cheap enough for ``--check`` (seconds each) -> what they print.
CHEAP: dict[str, Callable[[], list[str]]] = {
    "python benchmarks/figures.py --only kinematics": _this_script("--only", "kinematics"),
    "rpr-cosim run scenarios/pid_step.yaml --reference": _verb("run", "scenarios/pid_step.yaml", "--reference"),
}


def check(pages: list[Path]) -> int:
    """Compare every quoted output of the cheap commands in ``pages`` with what they print now."""
    bad, seen, cache = 0, 0, {}
    for page in pages:
        if page.resolve() == TUTORIAL:
            print(f"{page}: checked by `python -m docgen.tutorial` (tests/test_doc_pages.py runs it)")
            continue
        for lineno, command, body, dated in quoted_blocks(page):
            where = f"{page}:{lineno - 1}"
            if not dated:
                print(f"{where}: the quoted output of `{command}` says not when it was printed "
                      f"(a 'printed on DATE on MACHINE' line just above the block)")
                bad += 1
            if command not in CHEAP:
                print(f"{where}: not checked (expensive): {command}")
                continue
            seen += 1
            if command not in cache:
                cache[command] = CHEAP[command]()
            now = cache[command]
            for k, line, close in drifted(body, now):
                bad += 1
                print(f"{page}:{lineno + k}: quoted figure no longer printed by `{command}`:\n"
                      f"  page: {line}\n  now:  {close}")
    print(f"figures --check: {seen} quoted outputs checked, {bad} problem{'s' if bad != 1 else ''}")
    return 1 if bad else 0


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", action="store_true", help="also run the scenes (about two minutes)")
    ap.add_argument("--only", choices=sorted(SECTIONS), help="print only this section of the models' figures")
    ap.add_argument("--check", nargs="*", type=Path, metavar="PAGE",
                    help="check the quoted outputs in these pages (default: docs/**/*.md) against what the cheap "
                         "commands print now")
    ap.add_argument("--cache", type=Path, default=None, help="FMU cache (default: $RPR_COSIM_CACHE or a temporary one)")
    return ap.parse_args(argv)


def main() -> int:
    args = parse()
    if args.check is not None:
        return check(args.check or sorted((ROOT / "docs").rglob("*.md")))
    run(args)
    return 0


def run(args: argparse.Namespace) -> None:
    if args.only:
        SECTIONS[args.only]()
        return
    models_figures()
    if args.scenes:
        import os

        cache = args.cache or (Path(os.environ["RPR_COSIM_CACHE"]) if os.environ.get("RPR_COSIM_CACHE")
                               else Path(tempfile.mkdtemp(prefix="figures-")))
        scene_figures(cache)


if __name__ == "__main__":
    sys.exit(main())
