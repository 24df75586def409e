"""The exporter's error type."""
from __future__ import annotations


class BuildError(Exception):
    """A block that cannot be exported, or a failed FMU build; the message names the block and
    the variable (or the compiler log).  The command line reports it as one line, like a
    :class:`cosim.errors.UserError` (:func:`cosim.errors.user_error_types`)."""
