"""The recipe index of the FMU cache: a catalog component's recipe -> its cached FMU and interface.

The content key of :mod:`fmus.cache` hashes the *generated* C, so finding a cached FMU that way
means building the block and generating its code with CasADi first (tens of ms per FMU).  The
index answers the same question from what a scene writes: the **recipe** (model, fidelity as
written, construction options, the values of structural parameters, FMI version) plus a
**fingerprint** of everything else that could change the FMU: the sources of ``models/`` and
``fmus/`` (Python and the C core/wrappers), the FMI headers, the versions of CasADi, numpy, FMPy
and this package, the exporter version, the compiler (its path, size and modification time) and
its flags.  An entry is a JSON file ``<cache>/index/<key>.json`` holding the FMU's path (inside
the cache) and the interface a run needs: the block's parameters with units and bounds, its
variables, flanges, ratings and feedthrough, which states start at an exact value, and the FMU's
own description (value references, GUID, model identifier).  A run whose components are all in
the index therefore imports neither CasADi nor the exporter; anything else about a block (its
equations, for the monolithic reference or a study) builds the real block on first use.

A user's block (a scene's Python ``blocks:`` file or a Modelica file, :mod:`cosim.scenario.user_blocks`)
is indexed too: its recipe's ``sources`` hold the digests of what defines it (those files, the
front end's version) and enter the key, and its entry's ``depends`` lists every file its module
imported with its digest, checked at each hit, so an edit anywhere in them is a miss.

An entry is written after a build (:func:`record`) and never trusted beyond its fingerprint: any
change to a fingerprinted input gives another key (a miss: the block is built and its FMU found
by content, or compiled, as without the index).  The FMU behind a hit is verified (size, SHA-256)
before it is served; a missing or damaged one is rebuilt through the block.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
from dataclasses import asdict, dataclass
from functools import lru_cache
from importlib.util import find_spec
from pathlib import Path
from typing import Any

from models.interface import BlockError, Flange, Param, Rating, Var

from .cache import EXPORTER_VERSION, atomic_write, cache_root, stream_digest
from .compile import compiler_identity

INDEX_DIR = "index"
FORMAT = 1
#: Where the fingerprinted packages live (the repository or the installed tree).
SOURCE_ROOT = Path(__file__).resolve().parents[1]
_PACKAGES = ("models", "fmus")
_DISTS = {"casadi": "casadi", "numpy": "numpy", "fmpy": "fmpy", "rpr_cosim": "cosim"}
_FMI_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h",
                "fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")


# --- the fingerprint ------------------------------------------------------------------------------
def _normal(dist: str) -> str:
    return dist.lower().replace("-", "_").replace(".", "_")


def installed_version(dist: str, module: str | None = None) -> str | None:
    """The installed version of distribution ``dist`` (None when not installed), read from the
    name of its ``.dist-info`` folder beside the package ``module`` or on ``sys.path``, without
    importing anything (``importlib.metadata`` costs 20-50 ms of start-up)."""
    dirs = []
    spec = find_spec(module) if module else None
    if spec is not None and spec.origin:
        dirs.append(Path(spec.origin).resolve().parent.parent)
    dirs += [Path(p) for p in sys.path if p]
    want = _normal(dist)
    for d in dirs:
        try:
            names = os.listdir(d)
        except OSError:
            continue
        for name in names:
            if name.endswith(".dist-info"):
                project, _, version = name[:-len(".dist-info")].partition("-")
                if _normal(project) == want and version:
                    return version
    return None


@lru_cache(maxsize=1)
def fingerprint() -> str:
    """SHA-256 (hex) over every input of an FMU besides its recipe (module docstring)."""
    h = hashlib.sha256()

    def add(name: str, data: bytes) -> None:
        h.update(name.encode() + b"\0" + len(data).to_bytes(8, "little") + data)

    root = SOURCE_ROOT
    for pkg in _PACKAGES:
        for path in sorted((root / pkg).rglob("*")):
            if path.suffix in (".py", ".c", ".h") and "__pycache__" not in path.parts:
                add(str(path.relative_to(root)), path.read_bytes())
    fmpy = find_spec("fmpy")
    if fmpy is not None and fmpy.submodule_search_locations:
        headers = Path(list(fmpy.submodule_search_locations)[0]) / "c-code"
        for name in _FMI_HEADERS:
            try:
                add(f"fmi/{name}", (headers / name).read_bytes())
            except OSError:
                add(f"fmi/{name}", b"missing")
    for dist, module in _DISTS.items():
        add(f"dist/{dist}", str(installed_version(dist, module)).encode())
    add("exporter", EXPORTER_VERSION.encode())
    add("python", f"{sys.version_info[0]}.{sys.version_info[1]}".encode())
    add("compiler", compiler_identity().encode())
    return h.hexdigest()


# --- recipes and entries --------------------------------------------------------------------------
@dataclass(frozen=True)
class Recipe:
    """What a scene says about a catalog component's FMU: ``fidelity`` as written (None: the
    model's default), construction ``options`` as written, ``fixed`` structural parameter values."""

    model: str
    fidelity: str | None
    options: dict
    fixed: dict
    fmi: str
    #: a user's block (:mod:`cosim.scenario.user_blocks`): the digests of what defines it (the
    #: scene's Python block files, or the Modelica text and the front end's version); empty for
    #: the catalog, whose sources the fingerprint covers
    sources: dict = dataclasses.field(default_factory=dict)

    def key(self, fixed: dict | None = None) -> str:
        data = {"model": self.model, "fidelity": self.fidelity, "options": self.options,
                "fixed": {k: float(v) for k, v in (self.fixed if fixed is None else fixed).items()},
                "fmi": self.fmi, "fingerprint": fingerprint(), "format": FORMAT}
        if self.sources:
            data["sources"] = dict(self.sources)
        return hashlib.sha256(json.dumps(data, sort_keys=True, default=repr).encode()).hexdigest()[:32]


def index_dir(root: Path) -> Path:
    return Path(root) / INDEX_DIR


_PATHS: dict[tuple, Path] = {}  # (root, repr of the recipe) -> its entry's file


def _entry_path(root: Path, recipe: Recipe) -> Path:
    """The index file of ``recipe`` under ``root`` (its key hashed once per process)."""
    memo = (str(root), repr(recipe), fingerprint())
    path = _PATHS.get(memo)
    if path is None:
        path = _PATHS[memo] = index_dir(root) / f"{recipe.key()}.json"
    return path


_READ: dict[Path, tuple[tuple[int, int, int], dict | None]] = {}  # entry file -> ((mtime_ns, size, inode), entry)


def _read(path: Path) -> dict | None:
    """The entry in ``path`` (None when missing or not an entry), decoded once per process while
    the file is unchanged (a batch looks up the same few entries for every run); callers do not
    mutate it."""
    try:
        st = path.stat()
        stamp = (st.st_mtime_ns, st.st_size, st.st_ino)
        hit = _READ.get(path)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    entry = data if isinstance(data, dict) and data.get("format") == FORMAT else None
    _READ[path] = (stamp, entry)
    return entry


def lookup(model: str, fidelity: str | None, options: dict, params: dict, fmi: str,
           cache_dir: Path | None = None, *, sources: dict | None = None,
           rebuild=None) -> tuple[IndexedBlock, Recipe] | None:
    """The indexed block of a recipe (None on a miss).  ``params`` are the scene's parameter
    values: those the entry lists as structural select the entry of that variant.  A user's
    block gives its ``sources`` (:attr:`Recipe.sources`) and ``rebuild`` (a callable returning
    the real block); its entry also lists the files its module imported (``depends``), and a
    hit needs each of them unchanged."""
    root = cache_root(cache_dir, create=False)  # a lookup leaves the disk as it was
    base = Recipe(model, fidelity, dict(options), {}, fmi, dict(sources or {}))
    try:
        entry = _read(_entry_path(root, base))
        if entry is None:
            return None
        fixed = {k: params[k] for k in entry.get("structural", []) if k in params}
        recipe = dataclasses.replace(base, fixed=fixed)
        if fixed:
            entry = _read(_entry_path(root, recipe))
    except (TypeError, ValueError):  # options that do not serialise: no index for this recipe
        return None
    if entry is None or not entry.get("fmu") or not _unchanged(entry.get("depends") or {}):
        return None
    block = _indexed_block(entry, root)
    if rebuild is not None:
        block.rebuild = rebuild
    return block, recipe


def source_digest(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in blocks ("missing" when it cannot be read or is
    not a regular file: a device such as /dev/zero or a FIFO is never read)."""
    import os
    import stat

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return "missing"
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return "missing"
        return stream_digest(lambda n: os.read(fd, n))
    except OSError:
        return "missing"
    finally:
        os.close(fd)


def _unchanged(depends: dict) -> bool:
    return all(source_digest(Path(path)) == digest for path, digest in depends.items())


_BLOCKS: dict[tuple[int, Path], tuple[dict, "IndexedBlock"]] = {}


def _indexed_block(entry: dict, root: Path) -> "IndexedBlock":
    """One :class:`IndexedBlock` per decoded entry (so its real block, when needed, is built once)."""
    key = (id(entry), Path(root))
    hit = _BLOCKS.get(key)
    if hit is None or hit[0] is not entry:
        hit = _BLOCKS[key] = (entry, IndexedBlock(entry, root))
    return hit[1]


def record(recipe: Recipe, fidelity: str, block, fmu: Path, cache_dir: Path | None = None, *,
           description: dict | None = None, depends: dict | None = None) -> Path | None:
    """Write the index entry of ``recipe`` (its catalog ``fidelity`` resolved), whose block
    ``block`` was built into ``fmu`` (in the cache ``cache_dir``), with the FMU's
    ``description`` as the caller's plain data (:attr:`IndexedBlock.fmu_description`); returns the entry's path, or None when the cache cannot be written or
    the FMU is not inside it (nothing is lost: the next run takes the slow path)."""
    import casadi as ca

    from .cache import build_record

    root = cache_root(cache_dir).resolve()
    fmu = Path(fmu).resolve()
    if root not in fmu.parents:
        return None
    build = build_record(fmu)
    exact = [s.name for i, s in enumerate(block.states)
             if not (block.p.numel() and ca.depends_on(block.start[i], block.p))]
    entry = {"format": FORMAT, "recipe": asdict(recipe), "fidelity": fidelity, "fingerprint": fingerprint(),
             "fmu": str(fmu.relative_to(root)), "fmu_sha256": build.get("fmu_sha256"),
             "structural": [p.name for p in block.params if p.structural],
             "block": {"name": block.name, "fidelity": block.fidelity, "description": block.description,
                       "integrator": block.integrator, "substeps": int(block.substeps),
                       "sample_period": None if block.sample_period is None else float(block.sample_period),
                       "params": [asdict(p) for p in block.params], "inputs": [asdict(v) for v in block.inputs],
                       "outputs": [asdict(v) for v in block.outputs], "states": [asdict(v) for v in block.states],
                       "modes": [asdict(v) for v in getattr(block, "modes", [])],
                       "has_events": bool(getattr(block, "has_events", False)),
                       "flanges": [asdict(f) for f in block.flanges],
                       "ratings": {k: asdict(r) for k, r in block.ratings.items()},
                       "feedthrough": block.feedthrough(), "exact_start": exact},
             "fmu_description": description, "depends": dict(depends or {})}
    store_pending_replays()
    try:
        folder = index_dir(root)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{recipe.key()}.json"
        if not block.inputs:  # a source: the scene check samples its outputs over time (cosim.guards)
            from models.numeric import vectorize

            replayed = vectorize(block.functions()["out"]).to_data()
            atomic_write(folder / f"{recipe.key()}.out.json", json.dumps(replayed, default=_json_default).encode())
        atomic_write(path, json.dumps(entry, indent=1, default=_json_default).encode())
        if recipe.fixed:  # the base recipe tells which parameters are structural
            base = folder / f"{recipe.key({})}.json"
            if not base.exists():
                atomic_write(base, json.dumps({"format": FORMAT, "structural": entry["structural"],
                                               "fmu": None}).encode())
    except OSError:
        return None
    return path


def _json_default(x: Any) -> Any:
    if hasattr(x, "item"):
        return x.item()
    if isinstance(x, (tuple, set, frozenset)):
        return list(x)
    return repr(x)


# --- the indexed block ----------------------------------------------------------------------------
class IndexedBlock:
    """A catalog block as its index entry recorded it: the interface (name, fidelity,
    parameters, inputs, outputs, states, modes, flanges, ratings, feedthrough, integrator) without the
    equations.  Anything else (``p``, ``ode``, ``functions()``...) is read from the real block,
    built from the recipe on first use (:meth:`real`)."""

    def __init__(self, entry: dict, root: Path):
        b = entry["block"]
        self._entry, self.root = entry, Path(root)
        self.catalog_fidelity: str = entry["fidelity"]  # the catalog's name of the fidelity (resolved)
        self._real = None
        self.rebuild = None  # a user's block: how to build the real one (set by lookup)
        self.name, self.fidelity, self.description = b["name"], b["fidelity"], b["description"]
        self.integrator, self.substeps, self.sample_period = b["integrator"], b["substeps"], b["sample_period"]
        self.params = [Param(**p) for p in b["params"]]
        self.inputs, self.outputs, self.states = ([Var(**v) for v in b[k]] for k in ("inputs", "outputs", "states"))
        self.modes = [Var(**v) for v in b.get("modes", [])]
        self.has_events = bool(b.get("has_events", False))
        self.flanges = [Flange(**f) for f in b["flanges"]]
        self.ratings = {k: Rating(**r) for k, r in b["ratings"].items()}
        self.exact_start = frozenset(b["exact_start"])
        self._feedthrough = b["feedthrough"]

    # the recorded interface
    @property
    def fmu(self) -> Path:
        """The cached FMU this entry points to (verify it before use)."""
        return self.root / self._entry["fmu"]

    @property
    def fmu_description(self) -> dict | None:
        """The FMU's own description as recorded (plain data, see :func:`record`)."""
        return self._entry.get("fmu_description")

    @property
    def recipe(self) -> Recipe:
        return Recipe(**self._entry["recipe"])

    def feedthrough(self) -> dict[str, list[str]]:
        return {k: list(v) for k, v in self._feedthrough.items()}

    @property
    def param_defaults(self):
        import numpy as np

        return np.array([p.default for p in self.params], dtype=float)

    def param_vector(self, **values: float):
        """As :meth:`models.block.Block.param_vector`."""
        vec = self.param_defaults.copy()
        index = {p.name: i for i, p in enumerate(self.params)}
        for k, v in values.items():
            if k not in index:
                raise BlockError(f"block {self.name}: unknown parameter {k!r}; expected one of {', '.join(index)}")
            prm = self.params[index[k]]
            if not (prm.lower <= float(v) <= prm.upper):
                raise BlockError(f"block {self.name}: parameter {k!r} = {v} is outside [{prm.lower}, {prm.upper}]")
            vec[index[k]] = float(v)
        return vec

    def index(self, kind: str, name: str) -> int:
        """As :meth:`models.block.Block.index`."""
        for i, v in enumerate(getattr(self, kind)):
            if v.name == name:
                return i
        raise BlockError(f"block {self.name}: no {kind[:-1]} named {name!r}")

    def replay(self, function: str):
        """A numpy replay (:class:`models.numeric.NumpyFunction`) of the block's ``function``
        (``"out"``...), stored beside the entry on first use (that first use builds the block)."""
        from models.numeric import NumpyFunction, vectorize

        path = index_dir(self.root) / f"{self.recipe.key()}.{function}.json"
        data = _read_plain(path)
        if data is not None:
            return NumpyFunction.from_data(data)
        fn = vectorize(self.real().functions()[function])
        try:
            atomic_write(path, json.dumps(fn.to_data(), default=_json_default).encode())
        except OSError:
            pass
        return fn

    # everything else: the real block
    def real(self):
        """The real :class:`models.block.Block` (built from the recipe once)."""
        if self._real is None and self.rebuild is not None:
            self._real = self.rebuild()
        if self._real is None:
            import models.blocks as catalog

            r = self.recipe
            self._real = catalog.make(r.model, self.catalog_fidelity, **r.options, **r.fixed)
        return self._real

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.real(), name)

    def __repr__(self) -> str:
        return f"IndexedBlock({self.name}/{self.fidelity}, {self.fmu})"


def real_block(block):
    """The real block behind ``block`` (itself when it is not an :class:`IndexedBlock`)."""
    return block.real() if isinstance(block, IndexedBlock) else block


def _read_plain(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def replay(name: str, build) -> Any:
    """The numpy replay ``build()`` returns (a :class:`models.numeric.NumpyFunction` of a CasADi
    function that depends on the sources only, e.g. the kinematic det J), stored in the index
    under ``name`` and the fingerprint so that later processes need no CasADi."""
    from models.numeric import NumpyFunction

    path = index_dir(cache_root(create=False)) / f"fn-{fingerprint()[:24]}-{name}.json"
    if path in _PENDING_REPLAYS:
        return _PENDING_REPLAYS[path]
    data = _read_plain(path)
    if data is not None:
        return NumpyFunction.from_data(data)
    fn = _PENDING_REPLAYS[path] = build()  # stored with the next index entry: a scene check writes nothing
    return fn


#: replays computed in this process and not yet stored (path -> function); :func:`record` stores them
_PENDING_REPLAYS: dict[Path, Any] = {}


def store_pending_replays() -> None:
    """Store the replays :func:`replay` computed in this process (called once a run builds or
    starts, never by a scene check, which must leave the cache as it was)."""
    while _PENDING_REPLAYS:
        path, fn = _PENDING_REPLAYS.popitem()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, json.dumps(fn.to_data(), default=_json_default).encode())
        except OSError:
            pass


def cached_fmu(block: IndexedBlock, cache_dir: Path | None = None) -> tuple[Path | None, str]:
    """The FMU behind an indexed block when it is in ``cache_dir`` and intact: (path, "");
    else (None, why not)."""
    from .cache import verify

    if cache_root(cache_dir).resolve() != block.root.resolve():
        return None, "another cache"
    path = block.fmu
    if not path.is_file():
        return None, "missing"
    damage = verify(path)
    return (None, damage) if damage else (path, "")
