"""Access to the model catalog (:mod:`models.blocks`), loaded lazily, blocks cached."""
from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from typing import Any

from ..errors import UserError


def default_catalog():
    """The model catalog module :mod:`models.blocks`."""
    try:
        import models.blocks as blocks
    except ModuleNotFoundError as exc:
        if exc.name == "models.blocks":
            raise UserError("the model catalog (models.blocks) is not installed in this build; "
                            "only 'fmu:' components can be used") from None
        raise
    return blocks


@lru_cache(maxsize=64)
def _make(catalog, model: str, fidelity: str, frozen: tuple) -> Any:
    return catalog.make(model, fidelity, **dict(frozen))


def make_block(catalog, model: str, fidelity: str, options: Mapping[str, Any]):
    """``catalog.make`` with a cache keyed by the arguments (blocks are immutable in use)."""
    try:
        frozen = tuple(sorted((k, v if not isinstance(v, list) else tuple(v)) for k, v in options.items()))
        hash(frozen)
    except TypeError:
        return catalog.make(model, fidelity, **options)
    return _make(catalog, model, fidelity, frozen)
