"""Users' own components: Python block modules (a scene's ``blocks:`` files and the
``rpr_cosim.blocks`` entry point group) and Modelica files (a component's ``modelica:``).

A Python block module defines ``BLOCKS``: model name -> factory (one fidelity, ``default``) or
model name -> {fidelity: factory}; a factory's keyword arguments (with defaults) are the
model's construction options (``options:`` in the scene) and it returns a
:class:`models.block.Block` (:class:`models.user.BlockBuilder` writes one in a few lines).  An
entry point of the group ``rpr_cosim.blocks`` names a model and points to its factory, its
fidelity table or a module with ``BLOCKS``.  :class:`UserCatalog` offers them through the
interface of :mod:`models.blocks` (``catalog``, ``options``, ``make``).  A Modelica file is
read here and translated by :func:`models.modelica.translate`.
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import sys
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fmus.index import SOURCE_ROOT, source_digest
from ..errors import UserError
from ..readers import byte_limit, read_regular

ENTRY_POINT_GROUP = "rpr_cosim.blocks"


class UserBlockError(ValueError):
    """A user's block module or Modelica file that cannot be used (one line)."""


@dataclass(frozen=True)
class _Option:
    """A construction option of a user factory (the interface of :class:`models.blocks.Option`)."""

    name: str
    default: Any
    description: str

    def validate(self, where: str, value: Any) -> Any:
        return value


@dataclass
class _Model:
    fidelities: dict[str, Any]  # fidelity -> factory
    origin: str  # where it was defined (file or entry point), for messages
    source: str  # SHA-256 of the defining module's source ("" when unknown)
    depends: dict[str, str]  # the files its module imported (itself included) -> SHA-256


class UserCatalog:
    """The users' models, with the interface of :mod:`models.blocks` (``catalog``,
    ``options``, ``make``)."""

    def __init__(self) -> None:
        self.models: dict[str, _Model] = {}

    def add(self, table: Mapping, origin: str, source: str, reserved: set[str],
            depends: Mapping[str, str] | None = None) -> None:
        from models.user import blocks_of

        try:
            normal = blocks_of(table, origin)
        except ValueError as exc:
            raise UserBlockError(str(exc)) from None
        for model, fids in normal.items():
            if model in reserved:
                raise UserBlockError(f"{origin}: model {model!r} is a catalog model; give the user block another name")
            if model in self.models and self.models[model].origin != origin:
                raise UserBlockError(f"{origin}: model {model!r} is also defined by {self.models[model].origin}")
            self.models[model] = _Model(fids, origin, source, dict(depends or {}))

    def __contains__(self, model: object) -> bool:
        return model in self.models

    def catalog(self) -> dict[str, list[str]]:
        return {m: list(e.fidelities) for m, e in self.models.items()}

    def options(self, model: str, fidelity: str | None = None) -> dict[str, _Option]:
        factory = self._factory(model, fidelity)
        opts = {}
        for p in inspect.signature(factory).parameters.values():
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is not p.empty:
                opts[p.name] = _Option(p.name, p.default, f"construction option of {model} ({self.models[model].origin})")
        return opts

    def make(self, model: str, fidelity: str | None = None, **opts: Any):
        """The user's block: the factory called with its options, checked (documented, finite,
        well-formed), parameter defaults overridden by the other ``opts``."""
        from models.user import check_factory_result, with_defaults

        factory = self._factory(model, fidelity)
        fidelity = fidelity or next(iter(self.models[model].fidelities))
        where = f"{model} ({fidelity}, {self.models[model].origin})"
        known = self.options(model, fidelity)
        construction = {k: v for k, v in opts.items() if k in known}
        overrides = {k: v for k, v in opts.items() if k not in known}
        try:
            blk = factory(**construction)
        except ValueError as exc:  # a BlockError of the user's declarations
            raise UserBlockError(f"{where}: {exc}") from None
        except Exception as exc:  # the user's code failed: one line, with its own file and line
            raise UserBlockError(f"{where}: the factory raised {_one_line(exc)}") from None
        blk = check_factory_result(blk, where)
        return with_defaults(blk, where, overrides, list(known)) if overrides else blk

    def source(self, model: str) -> str:
        return self.models[model].source

    def depends(self, model: str) -> dict[str, str]:
        return dict(self.models[model].depends)

    def _factory(self, model: str, fidelity: str | None):
        fids = self.models[model].fidelities
        return fids[fidelity or next(iter(fids))]


def _one_line(exc: BaseException) -> str:
    """``Type: message (file:line)`` of the innermost frame of an exception."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" ({Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}{': ' + text if text else ''}{where}"


_DEPENDS: dict[str, dict[str, str]] = {}  # module name -> the files its import loaded


def load_module_file(path: Path):
    """Import the Python file ``path`` as a module (a fresh one for every content); returns the
    module and the SHA-256 of its source.  :func:`module_depends` then lists the files it imported."""

    try:
        data = read_regular(path, "blocks file")
    except UserError as exc:
        raise UserBlockError(str(exc)) from None
    name = f"rpr_user_blocks_{hashlib.sha256(str(path.resolve()).encode() + data).hexdigest()[:16]}"
    if name in sys.modules and all(source_digest(Path(f)) == d for f, d in _DEPENDS.get(name, {}).items()):
        return sys.modules[name], hashlib.sha256(data).hexdigest()  # imported before, nothing it loaded changed
    before = set(sys.modules) - {name}
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise UserBlockError(f"{path}: not a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    folder = str(path.resolve().parent)
    sys.path.insert(0, folder)  # a blocks file may import the modules beside it
    try:
        spec.loader.exec_module(module)
    except SyntaxError as exc:
        del sys.modules[name]
        raise UserBlockError(f"{path.name}:{exc.lineno}: syntax error: {exc.msg}") from None
    except (Exception, SystemExit, KeyboardInterrupt) as exc:  # the user's module failed (or exited) at import
        del sys.modules[name]
        raise UserBlockError(f"{path.name}: importing it raised {_import_failure(exc)}") from None
    finally:
        sys.path.remove(folder)
    files = {str(path.resolve()): hashlib.sha256(data).hexdigest()}
    for mod in set(sys.modules) - before:
        f = getattr(sys.modules.get(mod), "__file__", None)
        if f and _users_file(Path(f)):
            files[str(Path(f).resolve())] = source_digest(Path(f))
            if Path(f).resolve().parent == Path(folder) and mod != name:
                del sys.modules[mod]  # the next scene's file of that name is imported afresh
    _DEPENDS[name] = files
    return module, hashlib.sha256(data).hexdigest()


def _import_failure(exc: BaseException) -> str:
    """What a user's module did at import, in one line: an exception (RecursionError included),
    ``sys.exit()`` or a KeyboardInterrupt it raised itself."""
    if isinstance(exc, SystemExit):
        return f"SystemExit({exc.code!r}) (sys.exit() at import; a blocks file must only define BLOCKS)"
    if isinstance(exc, KeyboardInterrupt):
        return "KeyboardInterrupt (raised by the module at import)"
    return _one_line(exc)


def module_depends(module) -> dict[str, str]:
    """The files the import of a module of :func:`load_module_file` loaded (itself included),
    outside the Python installation and this project's packages (which the FMU cache's
    fingerprint covers): what a user's block depends on."""
    return dict(_DEPENDS.get(module.__name__, {}))


def _users_file(path: Path) -> bool:
    p = path.resolve()
    roots = {Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve()}
    roots |= {(SOURCE_ROOT / pkg).resolve() for pkg in ("models", "fmus", "cosim", "hardware")}
    return p.suffix == ".py" and not any(r == p or r in p.parents for r in roots) and "site-packages" not in p.parts



def module_table(module, origin: str) -> Mapping:
    table = getattr(module, "BLOCKS", None)
    if table is None:
        raise UserBlockError(f"{origin}: defines no BLOCKS (a mapping model name -> factory)")
    return table


def entry_point_catalog(reserved: set[str]) -> UserCatalog:
    """The models of the installed ``rpr_cosim.blocks`` entry points."""
    from importlib.metadata import entry_points

    cat = UserCatalog()
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        origin = f"entry point {ep.name} = {ep.value}"
        try:
            obj = ep.load()
        except (Exception, SystemExit, KeyboardInterrupt) as exc:
            raise UserBlockError(f"{origin}: loading it raised {_import_failure(exc)}") from None
        if inspect.ismodule(obj):
            table, src = module_table(obj, origin), _module_digest(obj)
        else:
            table, src = {ep.name: obj}, _module_digest(inspect.getmodule(obj))
        cat.add(table, origin, src, reserved)
    return cat


def _module_digest(module) -> str:
    path = getattr(module, "__file__", None)
    return source_digest(Path(path)) if path else ""


def read_modelica(path: Path) -> str:
    """The text of a Modelica file (:class:`UserBlockError` when it cannot be read)."""
    from models.modelica import MAX_SOURCE_BYTES

    env = "RPR_COSIM_MAX_MODELICA_BYTES"  # may lower the front end's own bound, not raise it
    try:
        return read_regular(path, "Modelica file", min(MAX_SOURCE_BYTES, byte_limit(env, MAX_SOURCE_BYTES)),
                            env).decode("utf-8")
    except UserError as exc:
        raise UserBlockError(str(exc)) from None
    except UnicodeDecodeError as exc:
        raise UserBlockError(f"{path.name}: cannot read it ({exc})") from None


def user_block(what: str, **options: Any):
    """A user's block named on the command line: ``FILE.mo:CLASS`` (a Modelica class; options
    ``integrator``, ``substeps``) or ``FILE.py:MODEL[/FIDELITY]`` (a Python block module; the
    factory's options and parameter overrides).  Returns ``(block, title, options)`` with the
    options as ``(name, default, description)``; :class:`UserBlockError` when it cannot be made."""
    from models.block import BlockError

    file, _, name = what.rpartition(":")
    path = Path(file)
    if not path.is_file():
        raise UserBlockError(f"{file}: no such file")
    try:
        if path.suffix == ".mo":
            from models.modelica import translate

            from .modelica_sources import SourceError, modelica_class, roots_from_env

            if not name:
                raise UserBlockError(f"{what}: name the Modelica class, e.g. {file}:Gear")
            try:
                mc = modelica_class(path.name, name, path.parent, [r for r in roots_from_env() if r.is_dir()])
            except SourceError as exc:
                raise UserBlockError(str(exc)) from None
            blk = translate(mc.text, name, path.name, name=name.split(".")[-1].lower(), compiled=mc.compiled(),
                            **{k: options[k] for k in ("integrator", "substeps") if k in options})
            return blk, f"{name}/modelica ({path.name})", [
                ("integrator", "auto", "exact when the equations are linear, else radau (auto, exact, rk4, radau)"),
                ("substeps", "1", "integrator substeps per communication step")]
        model, _, fidelity = name.partition("/")
        import models.blocks as catalog

        cat = UserCatalog()
        module, digest = load_module_file(path)
        cat.add(module_table(module, path.name), path.name, digest, set(catalog.catalog()), module_depends(module))
        if model not in cat:
            raise UserBlockError(f"{path.name} has no model {model!r} (BLOCKS: {', '.join(cat.models) or 'none'})")
        fid = fidelity or next(iter(cat.models[model].fidelities))
        if fid not in cat.models[model].fidelities:
            raise UserBlockError(f"{model} has no fidelity {fid!r} (expected one of "
                                 f"{', '.join(cat.models[model].fidelities)})")
        opts = [(o.name, str(o.default), o.description) for o in cat.options(model, fid).values()]
        return cat.make(model, fid, **options), f"{model}/{fid} ({path.name})", opts
    except BlockError as exc:
        raise UserBlockError(str(exc)) from None
