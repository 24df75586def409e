"""libcosimpy (libcosim's Python binding) as a test-only peer: run an OspSystemStructure.xml
(or an SSP) and sample real variables on a time grid."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np


def run(path: Path, times, variables: list[str], ssp: bool = False) -> dict:
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy._internal import get_last_error_message

    ex = CosimExecution.from_ssp_file(str(path)) if ssp else CosimExecution.from_osp_config_file(osp_path=str(path))
    obs = CosimObserver.create_last_value()
    ex.add_observer(obs)
    slaves = {i.name.decode(): i.index for i in ex.slave_infos()}
    refs = []
    for name in variables:
        comp, var = name.split(".", 1)
        vr = next(v.reference for v in ex.slave_variables(slaves[comp]) if v.name.decode() == var)
        refs.append((slaves[comp], vr))
    vals = np.zeros((len(times), len(variables)))
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        if not ex.simulate_until(round(t * 1e9)):
            raise RuntimeError(f"libcosim failed before {t} s: {get_last_error_message()}")
        vals[k] = [obs.last_real_values(i, [vr])[0] for i, vr in refs]
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "t": np.asarray(times), **{n: vals[:, j] for j, n in enumerate(variables)}}
