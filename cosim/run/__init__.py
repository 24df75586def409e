"""Running a scene: :func:`run` (a pure function of scene and overrides, :mod:`.execute`), the
run-time guards (:mod:`.guards`), the monolithic reference (:mod:`.reference`) and the SSP
export (:mod:`.ssp_export`, which builds the FMUs it packs)."""
from .execute import RunResult, build_components, run

__all__ = ["RunResult", "build_components", "run"]
