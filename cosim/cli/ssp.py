"""``rpr-cosim ssp``: scenes as SSP 1.0 archives.

    rpr-cosim ssp export SCENE.yaml [-o FILE.ssp] [--set PATH=VALUE ...] [--force] [--cache DIR]

The archive holds the scene's FMUs (from the cache; built on a miss), its parameters and start
values as a parameter set, its connections (a bond as its two signals), the default experiment and
our master settings as an annotation; it validates against the SSP 1.0 schemas and runs with
``rpr-cosim run FILE.ssp`` (or FMPy's ``fmpy.ssp.simulate_ssp``).  The path goes to stdout.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ssp", help="export a scene as an SSP 1.0 archive (run one with 'run FILE.ssp')",
                       description="Scenes as SSP 1.0 archives (System Structure and Parameterization).")
    verbs = p.add_subparsers(dest="ssp_verb", metavar="ACTION")
    verbs.required = True
    e = verbs.add_parser("export", help="write SCENE as FILE.ssp (FMUs, parameter set, connections, master)")
    e.add_argument("scene", type=Path, help="scene file, e.g. scenarios/pid_step.yaml")
    e.add_argument("-o", "--out", type=Path, help="archive to write (default <scene name>.ssp here)")
    e.add_argument("--set", dest="sets", action="append", default=[], metavar="PATH=VALUE",
                   help="override a scene value before export; repeatable")
    e.add_argument("--force", action="store_true", help="replace an existing archive")
    e.add_argument("--cache", type=Path, help="FMU cache directory (default $RPR_COSIM_CACHE or ~/.cache/rpr-cosim/fmus)")
    e.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> int:
    from ..scenario import SceneError, load
    from ..study.fidelity import resolve_auto
    from ..run.ssp_export import export

    try:
        scene = load(args.scene, args.sets, auto_fidelity=resolve_auto)
    except SceneError as exc:
        for p in exc.problems:
            print(p, file=sys.stderr)
        print(f"rpr-cosim ssp: {args.scene}: nothing was exported", file=sys.stderr)
        return 2
    dest = args.out or Path(f"{scene.name}.ssp")
    path = export(scene, dest, cache_dir=args.cache, overwrite=args.force,
                  progress=lambda m: print(f"[fmu] {m}", file=sys.stderr))
    print(path)
    return 0
