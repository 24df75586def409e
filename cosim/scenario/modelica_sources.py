"""The files a Modelica class is read from: the named file, then what its names reach through
the source roots, file by file.

A **source root** is a directory holding top-level classes as Modelica lays them out on disk
(``Modelica/package.mo`` with ``Modelica/Mechanics/package.mo`` and
``Modelica/Mechanics/Translational/Components/Mass.mo``, or a single ``Base.mo`` defining
``Base``), as OpenModelica's ``MODELICAPATH`` names them.  The roots of a component are, in
order: the directory of its file, the scene's ``modelica_path:`` and the environment's
``MODELICAPATH`` (colon-separated).

:func:`closure` reads the named file's names (every dotted identifier outside comments and
strings: ``extends``, ``import``, component types, function calls; a name that is not a class is
simply not found) and resolves each one as Modelica's lookup does, from the innermost enclosing
package of the file's ``within`` outwards to the roots; a name found adds the files along its
path (each enclosing ``package.mo``, then the file that defines it), whose names are read in
turn.  The result is what the front end is given (and nothing else: a sibling file that no name
reaches is never read, so it cannot shadow a class or slow the load) and what the cache key and
the scene hash cover (an edit of any of these files rebuilds the component).
"""
from __future__ import annotations

import gzip
import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from ..errors import UserError
from ..readers import byte_limit, read_regular
from fmus.cache import cache_root, writable_root

#: The environment variable OpenModelica reads for its library roots (colon-separated).
ENV_VAR = "MODELICAPATH"
#: The environment variable that may lower the size bound of a Modelica file (the MSL's largest is 1.1 MB).
MAX_BYTES_ENV = "RPR_COSIM_MAX_MODELICA_BYTES"
#: At most this many files in one class's closure (the MSL examples need 30-120).
MAX_FILES = 2000

_KEYWORDS = frozenset("""algorithm and annotation block break class connect connector constant constrainedby
der discrete each else elseif elsewhen encapsulated end enumeration equation expandable extends external false
final flow for function if import impure in initial inner input loop model not operator or outer output package
parameter partial protected public pure record redeclare replaceable return stream then true type when while
within Real Integer Boolean String time""".split())


class SourceError(ValueError):
    """A Modelica source that cannot be read (one line naming the file)."""


@dataclass
class Sources:
    """A class's files: ``main`` (the named file) and ``files`` (the others it reaches, in the
    order found); ``digests`` maps each file (main first) to its SHA-256."""

    main: Path
    roots: list[Path]
    files: list[Path] = field(default_factory=list)
    digests: dict[str, str] = field(default_factory=dict)

    def key(self) -> dict[str, str]:
        """The digests as a recipe's ``sources`` (file names relative to their root when under one)."""
        return {f"modelica:{self.label(Path(p))}": d for p, d in self.digests.items()}

    def label(self, path: Path) -> str:
        for root in self.roots:
            try:
                return str(path.relative_to(root))
            except ValueError:
                continue
        return path.name


def roots_from_env(environ: dict | None = None) -> list[Path]:
    """The directories of ``MODELICAPATH`` (empty entries skipped)."""
    value = (os.environ if environ is None else environ).get(ENV_VAR, "")
    return [Path(p) for p in value.split(os.pathsep) if p.strip()]


def read_text(path: Path) -> str:
    """The text of a regular Modelica file within the size bound (the front end's, which
    ``RPR_COSIM_MAX_MODELICA_BYTES`` may lower; :class:`SourceError` naming the file)."""
    from models.modelica import MAX_SOURCE_BYTES


    try:
        return read_regular(path, "Modelica file", min(MAX_SOURCE_BYTES, byte_limit(MAX_BYTES_ENV, MAX_SOURCE_BYTES)),
                            MAX_BYTES_ENV).decode("utf-8")
    except UserError as exc:
        raise SourceError(str(exc)) from None
    except UnicodeDecodeError as exc:
        raise SourceError(f"{path.name}: cannot read it ({exc})") from None


_CLASS_WORDS = frozenset(("model", "block", "class", "package", "connector", "record", "function", "type"))
_NOISE = re.compile(r'//[^\n]*|/\*.*?\*/|"(?:\\.|[^"\\])*"', re.S)  # comments and strings
_NAME = re.compile(r"(?<![\w.])([A-Za-z_]\w*(?:\s*\.\s*[A-Za-z_]\w*)*)")
_STRUCTURE = re.compile(r"\bwithin\s+([\w.\s]*);|\bend\s+([A-Za-z_]\w*)\s*;|"
                        r"(?<![\w.])(?:model|block|class|package|connector|record|function|type)\s+([A-Za-z_]\w*)"
                        r"\s*(=)?")


def _names(text: str) -> tuple[list[str], list[str], list[str], list[str]]:
    """``(within, top, members, names)``: the ``within`` package (as parts), the classes the
    file defines at its top, those one level in (a package's members) and every dotted name it
    uses."""
    clean = _NOISE.sub(" ", text)
    within: list[str] = []
    top: list[str] = []
    members: list[str] = []
    stack: list[str] = []
    for m in _STRUCTURE.finditer(clean):
        if m.group(1) is not None:
            if not stack:
                within = [p for p in re.split(r"\s*\.\s*", m.group(1).strip()) if p]
        elif m.group(2) is not None:
            if stack and m.group(2) == stack[-1]:
                stack.pop()
        else:
            start = clean.rfind("end", max(0, m.start() - 8), m.start())
            if start >= 0 and not clean[start + 3:m.start()].strip():
                continue  # 'end model' cannot happen, but 'end function' of an operator might
            if len(stack) <= 1:
                (members if stack else top).append(m.group(3))
            if m.group(4) is None:  # a long class definition, closed by 'end name;'
                stack.append(m.group(3))
    names = []
    for m in _NAME.finditer(clean):
        name = m.group(1)
        if any(c.isspace() for c in name):
            name = re.sub(r"\s+", "", name)
        if name.split(".", 1)[0] not in _KEYWORDS:
            names.append(name)
    return within, top, members, names


class _Resolver:
    """Maps qualified class names to the files along their path under the roots (memoised)."""

    def __init__(self, roots: Sequence[Path], texts: dict[Path, str]):
        self.roots = list(roots)
        self.texts = texts  # files read so far (shared with the closure)
        self.memo: dict[str, tuple[list[str], int]] = {}
        self.defined: dict[Path, set[str]] = {}
        self.dirs: dict[str, frozenset[str]] = {}  # directory -> its entries
        self.resolved: dict[tuple, list[str]] = {}

    def locate(self, qualified: list[str]) -> tuple[list[str], int]:
        """``(files, matched)``: the files along ``qualified`` in the first root holding its
        first part (each package's ``package.mo``, then a class's own file) and how many parts
        matched a directory or a file; the rest of the name is inside the last file."""
        key = ".".join(qualified)
        if key not in self.memo:
            best: tuple[list[str], int] = ([], 0)
            for root in self.roots:
                found = self._under(root, qualified)
                if found[1]:
                    best = found
                    break
            self.memo[key] = best
        return self.memo[key]

    def _under(self, root: Path, parts: list[str]) -> tuple[list[str], int]:
        files: list[str] = []
        here = str(root)
        for k, part in enumerate(parts):
            entries = self._listing(here)
            if part in entries and "package.mo" in self._listing(os.path.join(here, part)):
                here = os.path.join(here, part)
                files.append(os.path.join(here, "package.mo"))
            elif f"{part}.mo" in entries:
                files.append(os.path.join(here, f"{part}.mo"))
                return files, k + 1
            else:
                return files, k
        return files, len(parts)

    def _listing(self, directory: str) -> frozenset[str]:
        hit = self.dirs.get(directory)
        if hit is None:
            try:
                hit = frozenset(os.listdir(directory))
            except OSError:
                hit = frozenset()
            self.dirs[directory] = hit
        return hit

    def defines(self, path: Path, name: str) -> bool:
        """Whether the file ``path`` declares a class ``name`` at its top or one level in."""
        if path not in self.defined:
            self.defined[path] = set(_names(self.texts[path])[2]) if path in self.texts else set()
        return name in self.defined[path]

    def resolve(self, within: list[str], parts: list[str]) -> list[str]:
        """The files of ``parts`` looked up from the innermost package of ``within`` outwards
        (empty when it names no class of the roots)."""
        key = (tuple(within), tuple(parts))
        if key not in self.resolved:
            self.resolved[key] = self._resolve(within, parts)
        return self.resolved[key]

    def _resolve(self, within: list[str], parts: list[str]) -> list[str]:
        for k in range(len(within), -1, -1):
            files, matched = self.locate(within[:k] + parts)
            if matched > k:
                return files
            if k and files and matched == len(files) and self._nested(files, within[:k], parts[0]):
                return files
        return []

    def _nested(self, files: list[str], scope: list[str], first: str) -> bool:
        """Whether ``first`` is a class declared in the file holding the scope ``scope``."""
        last = Path(files[-1]) if files else None
        return last is not None and last in self.texts and self.defines(last, first)


def closure(main: Path, roots: Iterable[Path], main_text: str | None = None) -> Sources:
    """The files class names of ``main`` reach through ``roots`` (:class:`SourceError` when one
    cannot be read or there are more than :data:`MAX_FILES`)."""
    roots = [Path(r) for r in roots]
    src = Sources(main, roots)
    texts: dict[Path, str] = {}
    resolver = _Resolver(roots, texts)
    text = read_text(main) if main_text is None else main_text
    texts[main] = text
    src.digests[str(main)] = hashlib.sha256(text.encode()).hexdigest()
    queue: list[Path] = [main]
    seen = {os.path.realpath(main)}

    def add(files: list) -> None:
        for f in map(Path, files):
            real = str(f)
            if real in seen or os.path.realpath(f) in seen:
                continue
            seen.add(real)
            if len(seen) > MAX_FILES:
                raise SourceError(f"{main.name}: its classes reach more than {MAX_FILES} files")
            data = texts[f] = read_text(f)
            src.files.append(f)
            src.digests[str(f)] = hashlib.sha256(data.encode()).hexdigest()
            queue.append(f)

    while queue:
        within, top, members, names = _names(texts[queue.pop(0)])
        if within:  # the enclosing packages (their package.mo files), read before the names
            add(resolver.locate(within)[0])
        local = set(top) | set(members)
        for name in dict.fromkeys(names):
            parts = name.split(".")
            if parts[0] not in local:  # a class of this file hides any other of that name
                add(resolver.resolve(within, parts))
    return src


def class_file(qualified: str, roots: Iterable[Path]) -> Path | None:
    """The file defining the library class ``qualified`` (e.g. ``Modelica.Blocks.Sources.Sine``
    in ``Modelica/Blocks/Sources.mo``), None when no root holds its first part."""
    files, matched = _Resolver([Path(r) for r in roots], {}).locate(qualified.split("."))
    return Path(files[-1]) if matched and files else None




# --- a component's class, compiled once ----------------------------------------------------------
@dataclass
class ModelicaClass:
    """A Modelica component's class: ``model`` (qualified name) defined in ``sources.main``
    (a user's file or a library's), with everything it reads."""

    model: str
    text: str  # the main file's text
    sources: Sources
    library: bool  # the class was named by its qualified name (a class of the roots)

    @property
    def filename(self) -> str:
        return self.sources.label(self.sources.main) if self.library else self.sources.main.name

    def recipe_sources(self, front_end_version: str) -> dict[str, str]:
        """What the FMU's recipe key covers: every file's digest and the front end's version."""
        return {**self.sources.key(), "rumoca": front_end_version}

    def compiled(self, *, cache: Path | None = None) -> dict:
        """rumoca's result for the class (:func:`models.modelica.front_end`), from the disk cache
        when these exact files were compiled before (``cache``: the directory, default the FMU
        cache's ``modelica/``)."""
        from models.modelica import DAE_SCHEMA

        key = _compile_key(self, DAE_SCHEMA)
        hit = _MEMO.get(key)
        if hit is not None:
            return hit
        path = _cache_dir(cache) / f"{key}.json.gz"
        if path.is_file():
            try:
                hit = json.loads(gzip.decompress(path.read_bytes()))
            except (OSError, ValueError, EOFError):
                hit = None  # a damaged entry: compiled again and rewritten
        if hit is None:
            hit = _compile_in_view(self)
            try:
                from fmus.cache import atomic_write

                atomic_write(path, gzip.compress(json.dumps(hit).encode(), compresslevel=3))
            except OSError:
                pass  # a read-only cache: compiled again next time
        _MEMO[key] = hit
        return hit


_MEMO: dict[str, dict] = {}


def _cache_dir(cache: Path | None) -> Path:

    return writable_root(cache_root(cache) / "modelica")


def _compile_key(cls: ModelicaClass, schema: int) -> str:
    from fmus.index import installed_version

    h = hashlib.sha256(json.dumps([cls.model, cls.filename, str(installed_version("rumoca", "rumoca")), schema,
                                   sorted(cls.sources.key().items())]).encode())
    return h.hexdigest()[:32]


def _compile_in_view(cls: ModelicaClass) -> dict:
    """rumoca run on the class with a *view* of its roots as the only root: a temporary tree of
    links to the closure's files (the main file excepted: it is given as text), so rumoca reads
    exactly those.  A front-end error naming a file of the view names the real file."""
    from models.modelica import ModelicaError, front_end

    view = Path(tempfile.mkdtemp(prefix="rpr-modelica-view-"))
    try:
        links: dict[str, str] = {}
        files = [cls.sources.main, *cls.sources.files] if cls.library else cls.sources.files
        for f in files:
            rel = cls.sources.label(f)
            target = view / rel
            if target.exists():
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            os.symlink(f.resolve(), target)
            links[str(target)] = str(f)
        saved = os.environ.pop(ENV_VAR, None)  # rumoca reads MODELICAPATH itself: the view is all it may read
        try:
            if not cls.library:
                return front_end(cls.text, cls.model, cls.filename, (str(view),) if links else ())
            # a library's class is in the view (its file may be a package.mo the view needs); a
            # one-line model extending it is compiled, its variables named as the class's own
            wrapper = f"model RprCosimClass\n  extends {cls.model};\nend RprCosimClass;\n"
            return {**front_end(wrapper, "RprCosimClass", cls.filename, (str(view),)), "name": cls.model}
        except ModelicaError as exc:
            real = links.get(exc.filename)
            if real is None and exc.filename.startswith(str(view)):
                real = exc.filename[len(str(view)) + 1:]
            if real is not None:
                raise ModelicaError(real, exc.line, exc.message) from None
            raise
        finally:
            if saved is not None:
                os.environ[ENV_VAR] = saved
    finally:
        shutil.rmtree(view, ignore_errors=True)


def modelica_class(ref: str, model: str | None, base: Path, roots: Sequence[Path]) -> ModelicaClass:
    """The class of a component: ``ref`` a ``.mo`` file (relative to ``base``) with ``model``
    naming its class, or ``ref`` a qualified class name of the ``roots`` (``model`` then unused).
    :class:`SourceError` (one line) when it cannot be found or read."""
    if ref.endswith(".mo"):
        main = (base / ref)
        if not main.is_file():
            raise SourceError(f"Modelica file {ref!r} not found (looked in {main.parent})")
        text = read_text(main)
        cls = ModelicaClass(str(model), text, closure(main, [main.parent, *roots], text), library=False)
        from models.modelica import ModelicaError, bounded

        for f in [main, *cls.sources.files]:  # the user's own files, before rumoca sees them
            if _under_root(f, main.parent):
                try:
                    bounded(text if f == main else read_text(f), f.name)
                except ModelicaError as exc:
                    raise SourceError(str(exc)) from None
        return cls
    if not re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", ref):
        raise SourceError(f"{ref!r} is neither a .mo file nor a qualified Modelica class name "
                          f"(e.g. Modelica.Mechanics.Translational.Examples.Oscillator)")
    if not roots:
        raise SourceError(f"class {ref}: no Modelica source roots to find it in (set {ENV_VAR} or the scene's "
                          f"modelica_path: to the directory holding {ref.split('.')[0]}/)")
    main = class_file(ref, roots)
    if main is None:
        raise SourceError(f"class {ref}: no root holds {ref.split('.')[0]} (roots: "
                          f"{', '.join(str(r) for r in roots)})")
    text = read_text(main)
    root = next((r for r in roots if _under_root(main, r)), main.parent)
    return ModelicaClass(ref, text, closure(main, [root, *[r for r in roots if r != root]], text), library=True)


def _under_root(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


__all__ = ["ENV_VAR", "Sources", "SourceError", "closure", "class_file", "ModelicaClass", "modelica_class", "roots_from_env", "read_text"]
