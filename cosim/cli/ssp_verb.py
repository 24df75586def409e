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

from .verb import load_scene, refuse, tagged
from ..run.ssp_export import export
from ..scenario import SceneError


def _export(args: argparse.Namespace) -> int:

    try:
        scene = load_scene(args)
    except SceneError as exc:
        return refuse(exc, "ssp", args.scene, "nothing was exported", count=False)
    dest = args.out or Path(f"{scene.name}.ssp")
    path = export(scene, dest, cache_dir=args.cache, overwrite=args.force,
                  progress=tagged("fmu"))
    print(path)
    return 0
