"""User-facing error types: anything raised as one of these is printed as a one-line message."""
from __future__ import annotations


class UserError(Exception):
    """A mistake in the user's input (file, field or value); the message says what is expected."""


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types the CLI reports as one line (domain validation errors included)."""
    from models.block import BlockError
    from models.geometry import GeometryError

    return (UserError, GeometryError, BlockError, FileNotFoundError)
