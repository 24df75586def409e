"""User-facing error types: anything raised as one of these is printed as a one-line message."""
from __future__ import annotations

from fmus.errors import BuildError
from models.geometry import GeometryError


class UserError(Exception):
    """A mistake in the user's input (file, field or value); the message says what is expected."""


#: What a run, a batch row or a study row reports as its reason in one line: a user mistake, or
#: an FMU that could not be built (:class:`fmus.BuildError`, the exporter's own error type).
RUN_ERRORS: tuple[type[BaseException], ...] = (UserError, BuildError)


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types the CLI reports as one line (domain validation errors included)."""
    from models.block import BlockError

    return (UserError, BuildError, GeometryError, BlockError, FileNotFoundError)
