"""``rpr-cosim ssp``: scenes as SSP 1.0 archives.

    rpr-cosim ssp export SCENE.yaml [-o FILE.ssp] [--set PATH=VALUE ...] [--force] [--cache DIR]

The archive holds the scene's FMUs (from the cache; built on a miss), its parameters and start
values as a parameter set, its connections (a bond as its two signals), the default experiment and
our master settings as an annotation; it validates against the SSP 1.0 schemas and runs with
``rpr-cosim run FILE.ssp`` (or FMPy's ``fmpy.ssp.simulate_ssp``).  The path goes to stdout.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .options import add_actions, add_cache, add_out, add_scene, add_sets, add_verb
from .verb import load_scene, refuse, tagged


def register(sub: argparse._SubParsersAction) -> None:
    verbs = add_actions(sub, "ssp", "ssp_verb",
                        help="export a scene as an SSP 1.0 archive (run one with 'run FILE.ssp')",
                        description="Scenes as SSP 1.0 archives (System Structure and Parameterization).")
    e = add_verb(verbs, "export", _export,
                 help="write SCENE as FILE.ssp (FMUs, parameter set, connections, master)")
    add_scene(e)
    add_out(e, "archive to write (default <scene name>.ssp here)", "-o")
    add_sets(e, "override a scene value before export; repeatable")
    e.add_argument("--force", action="store_true", help="replace an existing archive")
    add_cache(e)


def _export(args: argparse.Namespace) -> int:
    from ..run.ssp_export import export
    from ..scenario import SceneError

    try:
        scene = load_scene(args)
    except SceneError as exc:
        return refuse(exc, "ssp", args.scene, "nothing was exported", count=False)
    dest = args.out or Path(f"{scene.name}.ssp")
    path = export(scene, dest, cache_dir=args.cache, overwrite=args.force,
                  progress=tagged("fmu"))
    print(path)
    return 0
