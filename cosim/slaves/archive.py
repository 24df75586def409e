"""What an FMU or SSP archive must be before anything reads or unpacks it: a zip whose member
names stay inside it (no absolute path, drive letter or ``..``), each once, no more than
:func:`limits` members and uncompressed bytes (counted from the archive's directory, before
extracting a byte).  The same check serves ``fmu check``, ``run`` (the FMU's unpacking) and
the SSP reader."""
from __future__ import annotations

import zipfile
from pathlib import Path

from ..errors import UserError
from ..readers import byte_limit
from ..readers import open_regular

#: Defaults: most members and uncompressed bytes of one archive (a generated FMU of this project
#: has ~10 members and ~1 MB; FMUs of other tools rarely exceed 100 MB).
MAX_MEMBERS = 10_000
MAX_BYTES = 500 * 10 ** 6
MEMBERS_ENV = "RPR_COSIM_MAX_ARCHIVE_MEMBERS"
BYTES_ENV = "RPR_COSIM_MAX_ARCHIVE_BYTES"


def limits() -> tuple[int, int]:
    """(members, uncompressed bytes) an archive may have: ``$RPR_COSIM_MAX_ARCHIVE_MEMBERS`` and
    ``$RPR_COSIM_MAX_ARCHIVE_BYTES`` (a number, or e.g. ``2GB``), else the defaults."""
    return byte_limit(MEMBERS_ENV, MAX_MEMBERS, "members"), byte_limit(BYTES_ENV, MAX_BYTES)


def _human(n: int) -> str:
    return f"{n / 1e6:,.1f} MB" if n >= 10 ** 6 else f"{n:,} bytes"


def archive_problem(path: Path, kind: str = "FMU", root_file: str | None = "modelDescription.xml") -> str | None:
    """Why ``path`` is not a ``kind`` archive one may open, or None: not a zip, a member whose
    name is absolute or climbs out with ``..``, a member listed twice, more members or
    uncompressed bytes than :func:`limits`, or no ``root_file`` at its root."""

    try:  # a FIFO would block the zip reader, a device feed it without end
        with open_regular(path, f"{kind} archive", 1 << 62):
            pass
    except UserError as exc:
        return str(exc).split(": ", 1)[-1]
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        return f"not an {kind}: not a zip archive ({exc})"
    max_members, max_bytes = limits()
    if len(infos) > max_members:
        return (f"unsafe {kind}: {len(infos):,} members, more than the limit of {max_members:,} "
                f"(${MEMBERS_ENV}); nothing was extracted")
    seen: set[str] = set()
    total = 0
    for info in infos:
        n = info.filename
        parts = n.replace("\\", "/").split("/")
        if n.startswith(("/", "\\")) or (len(n) > 1 and n[1] == ":") or ".." in parts:
            return f"unsafe {kind}: member {n!r} has an absolute path or '..'; an {kind}'s files are relative to its root"
        if n in seen:
            return f"unsafe {kind}: member {n!r} appears twice; which one counts would be up to the reader"
        seen.add(n)
        total += info.file_size
    if total > max_bytes:
        return (f"unsafe {kind}: its members unpack to {_human(total)}, more than the limit of {_human(max_bytes)} "
                f"(${BYTES_ENV}); nothing was extracted")
    if root_file and root_file not in seen:
        return f"not an {kind}: no {root_file} at the archive's root"
    return None


def check_archive(path: Path, kind: str = "FMU", root_file: str | None = "modelDescription.xml") -> None:
    """:func:`archive_problem` as a one-line :class:`UserError` naming ``path``."""
    problem = archive_problem(path, kind, root_file)
    if problem:
        raise UserError(f"{path}: {problem}")


__all__ = ["archive_problem", "check_archive", "limits"]
