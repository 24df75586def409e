"""The exporter's error type."""
from __future__ import annotations

from cosim.errors import UserError


class BuildError(UserError):
    """A block that cannot be exported, or a failed FMU build; the message names the block and
    the variable (or the compiler log)."""
