"""Compile generated C into the FMU's shared library and pack the ``.fmu`` archive; compile
programs (the board daemon) for this machine or a cross target (:data:`TARGETS`).

The library is built with ``-fvisibility=hidden``: only the ``fmi2*``/``fmi3*`` functions, which
the FMI headers mark visible, are exported, so many FMUs (and many instances) share one process.
:func:`exported_symbols` reads the dynamic symbol table back with ``nm`` to check it.
"""
from __future__ import annotations

import os
import platform
import re
import shutil
import subprocess
import zipfile
from functools import lru_cache
from pathlib import Path

from .errors import BuildError

#: Compiler flags (without the optimisation level); part of the cache key.
CFLAGS = ("-std=c99", "-fPIC", "-fvisibility=hidden", "-Wall", "-Wno-unused-variable",
          "-Wno-unused-function", "-Wno-unused-but-set-variable")
LDFLAGS = ("-shared", "-Wl,-z,defs", "-lm")
#: Generated C larger than this is compiled at -O1 (half the compile time, ~1.5x slower steps).
LARGE_SOURCE_BYTES = 400_000
#: A generated function larger than this is compiled at -O1 inside a file compiled at -O2
#: (:func:`large_functions_at_o1`): the unrolled factorisation of a big Radau block, called once
#: in many steps, while the functions every step runs get -O2.
LARGE_FUNCTION_BYTES = 400_000
_FUNCTION_START = re.compile(r"^static int casadi_f\d+\(.*\) \{$", re.M)


def optimisation(source_bytes: int) -> str:
    """``-O2``, or ``-O1`` for very large generated files (keeps big blocks' builds short)."""
    return "-O1" if source_bytes > LARGE_SOURCE_BYTES else "-O2"


def large_functions_at_o1(code: str) -> tuple[str, int]:
    """CasADi-generated ``code`` with every function larger than :data:`LARGE_FUNCTION_BYTES`
    wrapped in ``#pragma GCC optimize ("O1")`` (GCC and Clang accept it per function), and the
    number wrapped; the rest of the file then compiles at -O2 in reasonable time."""
    out, pos, wrapped = [], 0, 0
    for m in _FUNCTION_START.finditer(code):
        if m.start() < pos:
            continue
        end = code.find("\n}\n", m.end())
        if end < 0:
            break
        end += 3
        if end - m.start() > LARGE_FUNCTION_BYTES:
            out += [code[pos:m.start()], '#pragma GCC push_options\n#pragma GCC optimize ("O1")\n',
                    code[m.start():end], "#pragma GCC pop_options\n"]
            pos, wrapped = end, wrapped + 1
    out.append(code[pos:])
    return "".join(out), wrapped


#: Cross targets: name -> (compiler, Debian package, qemu-user runner, sysroot for the runner).
TARGETS = {"armhf": ("arm-linux-gnueabihf-gcc", "gcc-arm-linux-gnueabihf", "qemu-arm", "/usr/arm-linux-gnueabihf")}


def compiler(target: str = "host") -> str:
    """The C compiler for ``target``: ``$CC`` or ``gcc`` (``cc`` as a fallback) for ``"host"``;
    ``$CC_<TARGET>`` or the Debian cross compiler of :data:`TARGETS` otherwise."""
    if target == "host":
        cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
        if not cc:
            raise BuildError("no C compiler found: install gcc (Debian: apt-get install gcc) or set $CC")
        return cc
    if target not in TARGETS:
        raise BuildError(f"unknown build target {target!r}: expected host or {', '.join(TARGETS)}")
    name, package = TARGETS[target][:2]
    cc = os.environ.get(f"CC_{target.upper()}") or shutil.which(name)
    if not cc:
        raise BuildError(f"no cross compiler for {target}: install {package} (Debian: apt-get install {package}) "
                         f"or set $CC_{target.upper()}")
    return cc


def compiler_identity() -> str:
    """:func:`compiler`'s choice without running it: resolved path, size and modification time
    ("none" without a compiler); part of the FMU cache fingerprint and the run-time libraries' key."""
    try:
        cc = compiler()
    except BuildError:
        return "none"
    try:
        path = os.path.realpath(shutil.which(cc) or cc)
        st = os.stat(path)
    except OSError as exc:
        return f"{cc}: {exc}"
    return f"{path}:{st.st_size}:{st.st_mtime_ns}"


def runner(target: str = "host") -> list[str]:
    """The command prefix that runs a program built for ``target`` here: nothing for the host,
    qemu-user with the target's sysroot for a cross target (BuildError if qemu is missing)."""
    if target == "host":
        return []
    qemu, sysroot = TARGETS[target][2], TARGETS[target][3]
    path = shutil.which(qemu)
    if not path:
        raise BuildError(f"cannot run {target} programs here: install qemu-user (Debian: apt-get install qemu-user)")
    return [path, "-L", sysroot]


@lru_cache(maxsize=None)
def compiler_version(cc: str) -> str:
    """First line of ``cc --version`` (part of the cache key)."""
    try:
        out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
    except OSError as exc:
        raise BuildError(f"cannot run the C compiler {cc!r}: {exc}") from None
    return (out.stdout.splitlines() or ["unknown"])[0]


def platform_dirs() -> tuple[str, str]:
    """``binaries/`` folder names for FMI 2.0 and FMI 3.0 on this machine."""
    system = platform.system()
    machine = platform.machine().lower()
    if system == "Linux" and machine in ("x86_64", "amd64"):
        return "linux64", "x86_64-linux"
    if system == "Linux" and machine in ("aarch64", "arm64"):
        return "linux64", "aarch64-linux"  # FMI 2 has no standard aarch64 name
    if system == "Darwin":
        return "darwin64", f"{'aarch64' if machine == 'arm64' else 'x86_64'}-darwin"
    raise BuildError(f"building FMUs on {system}/{machine} is not supported (Linux and macOS are)")


def library_suffix() -> str:
    return ".dylib" if platform.system() == "Darwin" else ".so"


def _run_compiler(compile_cmds: list[tuple[str, list[str]]], link: list[str], what: str) -> None:
    """Compile (in parallel, one process each), then link; BuildError with the log's head.  The
    compilers run in process groups of their own, ended with this process's build: a signal (or
    any failure) here kills them too (the driver and its cc1/as/ld), not only this process."""
    procs: list[subprocess.Popen] = []
    errors = []
    try:
        procs += [_start(cmd) for _, cmd in compile_cmds]
        for proc in procs:
            out_text, err_text = proc.communicate()
            if proc.returncode != 0:
                errors.append((proc.returncode, (err_text or out_text).strip()))
        if not errors:
            proc = _start(link)
            procs.append(proc)
            out_text, err_text = proc.communicate()
            if proc.returncode != 0:
                errors.append((proc.returncode, (err_text or out_text).strip()))
    except BaseException:
        _stop_all(procs)
        raise
    if errors:
        code, log_text = errors[0]
        head = " | ".join(log_text.splitlines()[:6])
        raise BuildError(f"{what}: the C compiler failed (exit {code}): {head}")


def compile_library(src_dir: Path, sources: list[str], out: Path, *, block_name: str, opt: str = "-O2",
                    target: str = "host") -> None:
    """Compile ``sources`` (in parallel, one process each) and link them into ``out``; a failure
    raises :class:`BuildError` with the head of the compiler log."""
    cc = compiler(target)
    darwin = platform.system() == "Darwin" and target == "host"
    cmds = [(str(src_dir / (Path(s).stem + ".o")),
             [cc, opt, *CFLAGS, f"-I{src_dir}", "-c", str(src_dir / s), "-o", str(src_dir / (Path(s).stem + ".o"))])
            for s in sources]
    link = [cc, *[o for o, _ in cmds], "-o", str(out), *[f for f in LDFLAGS if not (darwin and "-z" in f)]]
    _run_compiler(cmds, link, f"block {block_name}")


#: Flags of programs (without the optimisation level); part of their cache key.
PROGRAM_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Wno-unused-parameter", "-Wno-format-truncation")


def compile_program(src_dir: Path, sources: list[str], out: Path, *, name: str, target: str = "host",
                    static: bool = False, opt: str = "-O2") -> None:
    """Compile and link the program ``out`` from ``sources`` for ``target`` (``static``: no
    shared libraries needed where it runs, e.g. a board with an older C library)."""
    cc = compiler(target)
    cmds = [(str(src_dir / (Path(s).stem + ".o")),
             [cc, opt, *PROGRAM_CFLAGS, f"-I{src_dir}", "-c", str(src_dir / s), "-o", str(src_dir / (Path(s).stem + ".o"))])
            for s in sources]
    link = [cc, *[o for o, _ in cmds], "-o", str(out), *(["-static"] if static else []), "-lm"]
    _run_compiler(cmds, link, name)


def _start(cmd: list[str]) -> subprocess.Popen:
    """A compiler process in a process group of its own (the driver and its cc1/as/ld children),
    so that :func:`_stop_all` ends all of them."""
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def _stop_all(procs: list[subprocess.Popen]) -> None:
    """Kill the process groups of ``procs`` still running and reap them."""
    import os
    import signal

    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    for p in procs:
        try:
            p.communicate(timeout=5)
        except (subprocess.TimeoutExpired, OSError, ValueError):
            pass


def exported_symbols(library: Path) -> list[str]:
    """Names of the functions and data a shared library exports (``nm -D --defined-only``)."""
    nm = shutil.which("nm")
    if not nm:
        raise BuildError("cannot list exported symbols: 'nm' (binutils) is not installed")
    res = subprocess.run([nm, "-D", "--defined-only", str(library)], capture_output=True, text=True)
    if res.returncode != 0:
        raise BuildError(f"nm failed on {library}: {res.stderr.strip()}")
    names = []
    for line in res.stdout.splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[1] in "TDBRVWtdbr":
            names.append(parts[2])
    return names


def pack(fmu: Path, members: dict[str, bytes]) -> None:
    """Write the ``.fmu`` zip with fixed timestamps (same inputs, same bytes)."""
    with zipfile.ZipFile(fmu, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(members):
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, members[name])
