"""Modelica models as blocks: a ``.mo`` text translated into a :class:`~models.block.Block`.

The front end is `rumoca <https://pypi.org/project/rumoca/>`_ (a Modelica compiler written in
Rust with a Python API; no OpenModelica needed): it parses, resolves, flattens and checks the
model and hands over its DAE as an expression graph (``Model.to_dict("dae")``), which this module
turns into CasADi SX.  rumoca's own ``casadi-ode`` target is not used because it refuses models
whose outputs are algebraic equations; its FMU targets are not used because the FMU is built by
our exporter (:mod:`fmus`: our integrators, our C core, strict FMI).

What a model may contain (anything else is refused with ``file:line: construct``):

- ``parameter Real`` with a value (a number, or an expression of other parameters: then it is
  computed, not settable), a ``unit`` and a description string; ``min``/``max`` become bounds;
- ``input Real`` / ``output Real`` with unit and description;
- continuous ``Real`` variables; those that appear in ``der()`` are states (start value from
  ``start``, a number or an expression of parameters; exported as ``state.<name>``);
- equations (acausal: the residuals are sorted and solved symbolically: one unknown at a time
  where an equation is linear in it, a linear algebraic loop by a symbolic sparse solve, a
  nonlinear one by Newton iterations unrolled into the generated code);
- types declared in the file (``type Force = Real(unit = "N")``, as ``Modelica.Units.SI`` does;
  the Modelica Standard Library itself is not loaded);
- the built-in functions sin, cos, tan, asin, acos, atan, atan2, sinh, cosh, tanh, exp, log,
  log10, sqrt, abs, sign, min, max, floor, ceil, smooth, noEvent, homotopy and if-expressions;
- connectors with one potential and one ``flow`` variable: each becomes a power-bond flange
  (:class:`~models.block.Flange`).  The potential is a velocity (``m/s``, ``rad/s``) or a position
  (``m``, ``rad``; then our flange carries its rate).  Which of the pair is an input is decided by
  the equations (the choice that leaves them solvable).  Sign: Modelica's flow variable is the
  force acting *on* this component; our effort is the force the ``effort_out`` side applies to
  its partner, so an ``effort_out`` flange exports ``-f`` (the same number Modelica's
  ``connect`` would hand to the partner) and a ``flow_out`` flange takes ``f`` as is.

Units: rumoca 0.10 does not check them, so the translation does (:class:`_Units`, with
:mod:`models.units`): the terms of a sum and the two sides of an equation must have the same SI
dimension, and the arguments of sin, exp, tanh... be dimensionless; a variable without a unit is
a wildcard, a number is a wildcard in a sum and a dimensionless factor in a product.

Refused: when-equations, algorithm sections and functions (their bodies are algorithms),
external functions, initial equations and algorithms, assert/terminate/reinit, event operators
(pre, edge, change, sample, delay), ``time`` (blocks are autonomous), discrete, Integer, Boolean
and String variables, inner/outer, stream connectors, arrays of connectors.

``models/`` is maths only: :func:`translate` takes the model's text; reading files is the
caller's (:mod:`cosim.scenario`).
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from itertools import product

import casadi as ca

from . import units
from .block import Block, BlockError
from .user import BlockBuilder

#: The rumoca DAE schema this translator reads (``Model.to_dict("dae")["schema_version"]``).
DAE_SCHEMA = 43
#: Newton iterations unrolled into the code for a nonlinear algebraic loop.
NEWTON_ITERATIONS = 12
#: A nonlinear loop is closed when its residual is below this, relative to ``1 + |z|``.
NEWTON_TOL = 1e-10
INTEGRATORS = ("auto", "exact", "rk4", "radau")


class ModelicaError(BlockError):
    """A model the translation cannot take: ``str()`` is ``file:line: what``."""

    def __init__(self, filename: str, line: int | None, message: str):
        self.filename, self.line, self.message = filename, line, message
        super().__init__(f"{filename}:{line}: {message}" if line else f"{filename}: {message}")


# --- what is refused, found in the text ----------------------------------------------------------
_UNSUPPORTED = {
    "when": "when-equations are not supported (events: blocks are continuous)",
    "elsewhen": "when-equations are not supported (events: blocks are continuous)",
    "algorithm": "algorithm sections are not supported (write equations)",
    "function": "function definitions are not supported (their bodies are algorithms; use the built-in "
                "functions or an expression)",
    "external": "external functions are not supported",
    "initial": "initial equations/algorithms are not supported (give start values)",
    "assert": "assert() is not supported", "terminate": "terminate() is not supported",
    "reinit": "reinit() is not supported (events)", "pre": "pre() is not supported (events)",
    "edge": "edge() is not supported (events)", "change": "change() is not supported (events)",
    "sample": "sample() is not supported (events)", "delay": "delay() is not supported",
    "time": "time is not supported (blocks are autonomous: their equations may not depend on time)",
    "discrete": "discrete variables are not supported",
    "Integer": "Integer variables are not supported (Real only)",
    "Boolean": "Boolean variables are not supported (Real only)",
    "String": "String variables are not supported (Real only)",
    "inner": "inner/outer is not supported", "outer": "inner/outer is not supported",
    "stream": "stream connectors are not supported",
    "import": "import is not supported (the Modelica Standard Library is not loaded: declare the SI types "
              "you use in the file, e.g. type Force = Real(unit = \"N\"))",
}
_TOKEN = re.compile(r'//[^\n]*|/\*.*?\*/|"(?:\\.|[^"\\])*"|[A-Za-z_][A-Za-z0-9_]*|\S', re.S)


def _tokens(text: str):
    """``(token, line)`` of the identifiers and symbols of ``text`` (comments and strings skipped)."""
    for m in _TOKEN.finditer(text):
        tok = m.group(0)
        if tok.startswith(("//", "/*", '"')):
            continue
        yield tok, text.count("\n", 0, m.start()) + 1


def unsupported(text: str, filename: str) -> None:
    """Raise :class:`ModelicaError` at the first construct the translation refuses."""
    toks = list(_tokens(text))
    for k, (tok, line) in enumerate(toks):
        if tok in _UNSUPPORTED:
            prev = toks[k - 1][0] if k else ""
            if prev == ".":  # a component's member named like a keyword-free builtin (a.time)
                continue
            if tok == "function" and prev == "end":
                continue
            raise ModelicaError(filename, line, f"{tok}: {_UNSUPPORTED[tok]}")


# --- the front end --------------------------------------------------------------------------------
_LOCATION = re.compile(r"\[([^\[\]\s]+?):(\d+):(\d+)\]")
_UNRESOLVED = re.compile(r"unresolved (?:component reference|name|type|class)[^']*'([^']+)'")


def _first_line(text: str, name: str) -> int | None:
    first = name.split(".")[0].split("[")[0]
    for tok, line in _tokens(text):
        if tok == first:
            return line
    return None


def _compile(text: str, model: str, filename: str):
    """rumoca's model of ``text`` (:class:`ModelicaError` with the line of a front-end error)."""
    try:
        import rumoca
    except ModuleNotFoundError:
        raise ModelicaError(filename, None, "Modelica components need the rumoca front end: pip install "
                                            "rumoca (the project's dependencies include it)") from None
    try:
        return rumoca.Session().loads(text, model=model, filename=filename)
    except rumoca.RumocaError as exc:
        msg = str(exc)
        first = msg.splitlines()[0] if msg else type(exc).__name__
        first = re.sub(r"^\S+ could not be compiled: ", "", first)
        loc = _LOCATION.search(msg)
        line = int(loc.group(2)) if loc else None
        if line is None:  # the compiler's summary has no location: its diagnostics do
            for d in rumoca.validate_source(text, model=model, filename=filename):
                where = _LOCATION.search(d.message or "")
                if d.level == "error" and where:
                    line = int(where.group(2))
                    break
        for d in getattr(exc, "diagnostics", []) or []:
            if line is None and d.line and d.line > 1:
                line = d.line
        if line is None:
            unresolved = _UNRESOLVED.search(msg)
            if unresolved:
                line = _first_line(text, unresolved.group(1))
        if line is None and model and model not in _classes(text) and model.split(".")[-1] not in _classes(text):
            first = f"{first} (the file defines {', '.join(_classes(text)) or 'no class'})"
        raise ModelicaError(filename, line, first.strip().rstrip(":")) from None


# --- bounds and crash isolation of the front end (issue 33) -----------------------------------------
#: Most bytes of one Modelica source, most operators in one statement and most nested
#: parentheses: checked on the text before rumoca sees it (a 5,000-term sum crashes rumoca with
#: SIGSEGV; 500 terms overflow the translation's recursion).
MAX_SOURCE_BYTES = 2 * 10 ** 6
MAX_OPERATORS = 400
MAX_NESTING = 64
_OPERATORS = frozenset("+-*/^") | {".+", ".-", ".*", "./", ".^", "and", "or"}


def bounded(text: str, filename: str) -> None:
    """Raise :class:`ModelicaError` (with the line) when ``text`` exceeds :data:`MAX_SOURCE_BYTES`,
    a statement has more than :data:`MAX_OPERATORS` operators or parentheses and brackets nest
    deeper than :data:`MAX_NESTING`."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_SOURCE_BYTES:
        raise ModelicaError(filename, None, f"{len(text):,} characters, more than the limit of "
                                            f"{MAX_SOURCE_BYTES:,} bytes for one Modelica file")
    ops = depth = 0
    start = None  # the line of the statement's first token
    for tok, line in _tokens(text):
        start = start or line
        if tok == ";":
            ops, start = 0, None
        elif tok in "([{":
            depth += 1
            if depth > MAX_NESTING:
                raise ModelicaError(filename, line, f"parentheses nested more than {MAX_NESTING} deep; split the "
                                                    f"expression")
        elif tok in ")]}":
            depth = max(0, depth - 1)
        elif tok in _OPERATORS:
            ops += 1
            if ops > MAX_OPERATORS:
                raise ModelicaError(filename, start, f"a statement with more than {MAX_OPERATORS} operators; split "
                                                     f"it into several equations (intermediate variables)")


_FRONT_END: dict[tuple[str, str, str], tuple[dict, dict, str]] = {}  # (sha256, model, file) -> result


def front_end(text: str, model: str, filename: str) -> tuple[dict, dict, str]:
    """``(dae, flat, model name)``: rumoca's DAE and flat dictionaries of ``model`` in ``text``,
    compiled in a forked child so that a crash of the compiler (a signal) is one
    :class:`ModelicaError`, not the death of the workbench.  rumoca is imported once in this
    process (the child inherits it); results are kept per source, model and file name, so a
    second component of the same class compiles nothing."""
    import hashlib
    import os
    import pickle
    import signal

    key = (hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest(), model, filename)
    if key in _FRONT_END:
        return _FRONT_END[key]
    try:
        import rumoca  # noqa: F401  (loaded here once, inherited by every child)
    except ModuleNotFoundError:
        pass  # _compile says so in one line
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: compile, send the result or the error, exit without cleanup
        code = 0
        try:
            import faulthandler

            faulthandler.disable()  # a crash is the parent's one line, not a dump of the child's stack
            os.close(read)
            try:
                m = _compile(text, model, filename)
                out = ("ok", (m.to_dict("dae"), m.to_dict("flat"), m.name))
            except ModelicaError as exc:
                out = ("error", (exc.filename, exc.line, exc.message))
            except BaseException as exc:  # noqa: BLE001 - anything else, in one line
                out = ("error", (filename, None, f"the Modelica front end failed: {type(exc).__name__}: "
                                                 f"{str(exc).splitlines()[0] if str(exc) else ''}"))
            with os.fdopen(write, "wb") as fh:
                pickle.dump(out, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException:  # noqa: BLE001
            code = 1
        os._exit(code)
    os.close(write)
    with os.fdopen(read, "rb") as fh:
        data = fh.read()
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or not data:
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
        how = f"died of {signal.Signals(sig).name} (signal {sig})" if sig else f"exited ({os.waitstatus_to_exitcode(status)})"
        raise ModelicaError(filename, None, f"the Modelica front end (rumoca) {how} while compiling {model}; "
                                            f"simplify the model (long or deeply nested expressions)")
    kind, payload = pickle.loads(data)
    if kind == "error":
        raise ModelicaError(*payload)
    _FRONT_END[key] = payload
    return payload


def _classes(text: str) -> list[str]:
    toks = [t for t, _ in _tokens(text)]
    return [toks[i + 1] for i, t in enumerate(toks[:-1])
            if t in ("model", "block", "class", "package") and (i == 0 or toks[i - 1] != "end")]


# --- the DAE expression graph as CasADi -----------------------------------------------------------
_BINARY = {
    "add": lambda a, b: a + b, "subtract": lambda a, b: a - b, "multiply": lambda a, b: a * b,
    "divide": lambda a, b: a / b, "power": lambda a, b: a ** b,
    "greater": lambda a, b: a > b, "less": lambda a, b: a < b, "greater_equal": lambda a, b: a >= b,
    "less_equal": lambda a, b: a <= b, "greater_or_equal": lambda a, b: a >= b,
    "less_or_equal": lambda a, b: a <= b, "equal": lambda a, b: a == b, "not_equal": lambda a, b: a != b,
    "and": ca.logic_and, "or": ca.logic_or,
}
_UNARY = {"negate": lambda a: -a, "plus": lambda a: a, "not": ca.logic_not}
_BUILTIN = {
    "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "asin": ca.asin, "acos": ca.acos, "atan": ca.atan,
    "atan2": ca.atan2, "sinh": ca.sinh, "cosh": ca.cosh, "tanh": ca.tanh, "exp": ca.exp, "log": ca.log,
    "log10": lambda a: ca.log(a) / math.log(10.0), "sqrt": ca.sqrt, "abs": ca.fabs, "sign": ca.sign,
    "min": ca.fmin, "max": ca.fmax, "floor": ca.floor, "ceil": ca.ceil,
    "smooth": lambda order, a: a, "no_event": lambda a: a, "homotopy": lambda actual, simplified: actual,
}


@dataclass
class _Graph:
    """The DAE's expression nodes, evaluated lazily into SX with ``env`` for the coordinates."""

    nodes: list
    operands: list
    starts: list  # first operand of each node
    env: dict
    line_of: object  # node index -> source line
    filename: str
    names: dict  # variable index -> name (for messages)

    def __post_init__(self):
        self.memo: dict[int, ca.SX] = {}

    def __call__(self, i: int) -> ca.SX:
        hit = self.memo.get(i)
        if hit is None:
            hit = self.memo[i] = self._eval(i)
        return hit

    def _eval(self, i: int) -> ca.SX:
        (kind, body), = self.nodes[i].items()
        if kind == "literal":
            (t, v), = body.items()
            if t not in ("real", "integer"):
                self._refuse(i, f"a {t} literal is not supported (Real only)")
            return ca.SX(float(v))
        if kind == "coordinate":
            key = next(iter(body.items()))
            if key not in self.env:
                self._refuse(i, f"{key[0]} is not supported here")
            return self.env[key]
        if kind == "binary":
            op = _BINARY.get(body["operator"])
            if op is None:
                self._refuse(i, f"operator {body['operator']} is not supported")
            return op(self(body["lhs"]), self(body["rhs"]))
        if kind == "unary":
            op = _UNARY.get(body["operator"])
            if op is None:
                self._refuse(i, f"operator {body['operator']} is not supported")
            return op(self(body["operand"]))
        args = [self(self.operands[self.starts[i] + k]) for k in range(body.get("operand_count", 0))]
        if kind == "builtin":
            fn = _BUILTIN.get(body["builtin"])
            if fn is None:
                self._refuse(i, f"the function {body['builtin']}() is not supported")
            return fn(*args)
        if kind == "conditional":  # (c1, v1, c2, v2, ..., else)
            value = args[-1]
            for k in range(len(args) - 3, -1, -2):
                value = ca.if_else(args[k], args[k + 1], value)
            return value
        self._refuse(i, f"the expression kind {kind!r} is not supported")

    def _refuse(self, i: int, what: str):
        raise ModelicaError(self.filename, self.line_of(i), what)


_SAME = ("add", "subtract", "greater", "less", "greater_equal", "less_equal", "greater_or_equal",
         "less_or_equal", "equal", "not_equal")
_DIMENSIONLESS_ARG = ("sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh", "exp", "log", "log10")


class _Units:
    """The unit check of the DAE's expressions: every sum, comparison, min/max and branch of an
    if-expression must add like units, and the built-in functions' arguments be dimensionless.
    A variable without a unit (or with a symbol :mod:`models.units` does not know) and a number
    in a sum are wildcards; a number in a product is a dimensionless factor."""

    def __init__(self, graph: _Graph, var_units: dict[int, str]):
        self.g = graph
        self.units = {k: units.parse(u) for k, u in var_units.items()}
        self.declared = var_units
        self.memo: dict[int, tuple] = {}

    def __call__(self, i: int):
        """``(dims or None, is_number, label)`` of node ``i``."""
        hit = self.memo.get(i)
        if hit is None:
            hit = self.memo[i] = self._eval(i)
        return hit

    def _eval(self, i: int):
        (kind, body), = self.g.nodes[i].items()
        if kind == "literal":
            return None, True, "a number"
        if kind == "coordinate":
            (what, k), = body.items()
            d = self.units.get(k)
            label = f"{self.g.names.get(k, '?')} [{self.declared.get(k) or 'no unit'}]"
            if what == "derivative" and d is not None:
                return units.times(d, units.parse("s"), -1), False, f"der({self.g.names.get(k, '?')}) " \
                                                                     f"[{self.declared.get(k)}/s]"
            return d, False, label
        if kind == "binary":
            op = body["operator"]
            a, b = self(body["lhs"]), self(body["rhs"])
            if op in _SAME:
                d = self._same(i, op, a, b)
                return (d if op in ("add", "subtract") else None), a[1] and b[1], self._label(d)
            if op in ("multiply", "divide"):
                da = units.ONE if a[1] else a[0]
                db = units.ONE if b[1] else b[0]
                if da is None or db is None:
                    return None, a[1] and b[1], "?"
                d = units.times(da, db, 1 if op == "multiply" else -1)
                return d, a[1] and b[1], self._label(d)
            if op == "power":
                e = self.g(body["rhs"])
                if a[0] is None or not e.is_constant():
                    return None, a[1], "?"
                d = units.power(a[0], Fraction(float(ca.evalf(e))).limit_denominator(64))
                return d, a[1], self._label(d)
            return None, False, "?"
        if kind == "unary":
            a = self(body["operand"])
            return (a if body["operator"] in ("negate", "plus") else (None, False, "?"))
        args = [self(self.g.operands[self.g.starts[i] + k]) for k in range(body.get("operand_count", 0))]
        if kind == "conditional":
            d = None
            for v in args[1::2] + [args[-1]]:
                d = self._same(i, "if-expression", (d, d is None, self._label(d)), v) if d is not None else v[0]
            return d, False, self._label(d)
        if kind == "builtin":
            name = body["builtin"]
            if name in _DIMENSIONLESS_ARG:
                a = args[0]
                if a[0] is not None and a[0] != units.ONE:
                    self._fail(i, f"the argument of {name}() is {a[2]}; expected a dimensionless value")
                return units.ONE, False, "1"
            if name in ("min", "max", "atan2", "homotopy"):
                d = self._same(i, f"{name}()", args[0], args[1])
                return (units.ONE if name == "atan2" else d), False, self._label(d)
            if name == "sqrt" and args[0][0] is not None:
                d = units.power(args[0][0], Fraction(1, 2))
                return d, False, self._label(d)
            if name in ("abs", "floor", "ceil", "no_event"):
                return args[0]
            if name == "smooth":
                return args[1]
            if name == "sign":
                return units.ONE, False, "1"
        return None, False, "?"

    @staticmethod
    def _label(d) -> str:
        return "?" if d is None else f"[{units.text(d)}]"

    def _same(self, i: int, op: str, a, b):
        if a[0] is not None and b[0] is not None and a[0] != b[0] and not (a[1] or b[1]):
            what = {"add": "'+'", "subtract": "an equation or '-'"}.get(op, op)
            self._fail(i, f"unit mismatch in {what}: {a[2]} against {b[2]} (in SI base units {units.text(a[0])} "
                          f"against {units.text(b[0])})")
        return a[0] if a[0] is not None and not a[1] else b[0]

    def _fail(self, i: int, what: str):
        raise ModelicaError(self.g.filename, self.g.line_of(i), what)


def _operand_starts(nodes: list) -> list[int]:
    """Where each node's operands begin in the DAE's shared operand list (consumed in node order)."""
    starts, k = [], 0
    for n in nodes:
        starts.append(k)
        (_, body), = n.items()
        if isinstance(body, dict) and "operand_count" in body:
            k += body["operand_count"]
    return starts


# --- translation ----------------------------------------------------------------------------------
_POSITION_UNITS = ("m", "rad")
_VELOCITY_UNITS = ("m/s", "rad/s")


def translate(text: str, model: str, filename: str = "model.mo", *, name: str | None = None,
              integrator: str = "auto", substeps: int = 1) -> Block:
    """The :class:`Block` of Modelica ``model`` in ``text`` (``filename`` names it in messages).

    ``name`` is the block's name (default: the model's last name part, lower case);
    ``integrator`` is ``"auto"`` (``exact`` when the equations are linear, else ``radau``),
    ``exact``, ``rk4`` or ``radau``.  Raises :class:`ModelicaError` (``file:line: what``)."""
    if integrator not in INTEGRATORS:
        raise ModelicaError(filename, None, f"integrator {integrator!r}; expected one of {', '.join(INTEGRATORS)}")
    bounded(text, filename)
    unsupported(text, filename)
    dae, flat, model_name = front_end(text, model, filename)
    if dae.get("schema_version") != DAE_SCHEMA:
        raise ModelicaError(filename, None, f"rumoca {_rumoca_version()} writes DAE schema "
                                            f"{dae.get('schema_version')}; this translator reads schema {DAE_SCHEMA} "
                                            f"(rumoca 0.10.x)")
    return _Translation(text, filename, dae["storage"], flat, model_name, name or model.split(".")[-1].lower()).block(
        integrator, substeps)


def _rumoca_version() -> str:
    import rumoca

    return rumoca.version()


class _Translation:
    def __init__(self, text: str, filename: str, st: dict, flat: dict, model_name: str, name: str):
        self.text, self.filename, self.st, self.flat, self.name = text, filename, st, flat, name
        self.description = (flat.get("model_description") or "").strip() or f"Modelica model {model_name}"
        self.vars = st["variables"]
        ex = st["expressions"]
        self.nodes, self.prov = ex["nodes"], ex["provenance"]
        self.env: dict = {}
        self.graph = _Graph(self.nodes, ex["operands"], _operand_starts(self.nodes), self.env, self._node_line,
                            filename, {k: v["name"] for k, v in enumerate(self.vars)})
        self.units = _Units(self.graph, {k: (v["attributes"].get("unit") or "") for k, v in enumerate(self.vars)})

    # source lines
    def _offset_line(self, offset: int | None) -> int | None:
        return None if offset is None else self.text.count("\n", 0, offset) + 1

    def _node_line(self, i: int) -> int | None:
        span = (self.prov[i] or {}).get("span") if i < len(self.prov) else None
        return self._offset_line(span.get("start")) if span else None

    def _var_line(self, v: dict) -> int | None:
        span = (v.get("declaration") or {}).get("span")
        return self._offset_line(span.get("start")) if span else _first_line(self.text, v["name"])

    def _err(self, v: dict | None, what: str):
        raise ModelicaError(self.filename, self._var_line(v) if v else None, what)

    def _constant(self, node: int | None, v: dict, what: str) -> float | None:
        if node is None:
            return None
        e = self.graph(node)
        if not e.is_constant():
            self._err(v, f"{v['name']}: {what} must be a number")
        return float(ca.evalf(e))

    # the block
    def block(self, integrator: str, substeps: int) -> Block:
        self._refuse_flat()
        b = BlockBuilder(self.name, self.description, fidelity="modelica")
        roles: dict[str, list[int]] = {}
        for k, v in enumerate(self.vars):
            roles.setdefault(v["role"], []).append(k)
        bad = sorted(set(roles) - {"parameter", "input", "output", "state", "algebraic"})
        if bad:
            v = self.vars[roles[bad[0]][0]]
            self._err(v, f"{v['name']}: a {bad[0].replace('_', ' ')} variable is not supported (continuous Real only)")
        for k in roles.get("parameter", []):
            self._parameter(b, k)
        for k in roles.get("input", []):
            v = self.vars[k]
            self.env[("input", k)] = b.input(v["name"], *self._doc(v, "input"))
        states = roles.get("state", [])
        unknown: dict[tuple, ca.SX] = {}
        for k in states:
            v = self.vars[k]
            unit, text = self._doc(v, "state")
            start = v["attributes"].get("start")
            s0 = self.graph(start) if start is not None else ca.SX(0.0)
            if ca.depends_on(s0, ca.vertcat(*[self.env[("input", j)] for j in roles.get("input", [])])) \
                    if roles.get("input") else False:
                self._err(v, f"{v['name']}: the start value may depend on parameters only")
            self.env[("state", k)] = b.state(f"state.{v['name']}", s0, unit, text)
            unknown[("derivative", k)] = ca.SX.sym(f"der_{v['name']}")
        for k in roles.get("output", []) + roles.get("algebraic", []):
            unknown[("algebraic", k)] = ca.SX.sym(self.vars[k]["name"])  # outputs are algebraic coordinates too
        self.env.update(unknown)
        flanges = self._connectors()
        residuals = self._residuals()
        solved, chosen = self._solve(b, residuals, unknown, flanges)
        for k in states:
            b.der(self.env[("state", k)], solved[("derivative", k)])
        value = {key[1]: solved[key] if key in solved else self.env[key] for key in unknown if key[0] != "derivative"}
        for k in states:
            value[k] = self.env[("state", k)]
        emit = [(k, lambda k=k: b.output(self.vars[k]["name"], value[k], *self._doc(self.vars[k], "output")))
                for k in roles.get("output", []) + [j for j in states if self._is_output(self.vars[j])]]
        emit += [(min(fl["potential"], fl["flow"]), lambda fl=fl, c=c: self._flange(b, fl, c, value))
                 for fl, (c, _) in zip(flanges, chosen)]
        for _, add in sorted(emit, key=lambda e: e[0]):  # in declaration order
            add()
        return self._finish(b, integrator, substeps)

    def _finish(self, b: BlockBuilder, integrator: str, substeps: int) -> Block:
        if integrator != "auto":
            return b.build(integrator=integrator, substeps=substeps)
        from .integrators import affine_parts

        probe = b.build(integrator="rk4", substeps=substeps)  # (building does not change the builder)
        if not probe.states or affine_parts(probe) is not None:
            exact = dataclasses.replace(probe, integrator="exact" if probe.states else "none")
            exact.check()
            return exact
        return b.build(integrator="radau", substeps=substeps)

    @staticmethod
    def _is_output(v: dict) -> bool:
        return v["attributes"].get("causality") == "output"

    def _doc(self, v: dict, kind: str) -> tuple[str, str]:
        a = v["attributes"]
        unit, text = (a.get("unit") or "").strip(), (a.get("description") or "").strip()
        if not unit:
            self._err(v, f"{kind} {v['name']!r} has no unit (declare it, e.g. Real {v['name']}(unit = \"1\") or "
                         f"a type such as type Force = Real(unit = \"N\"))")
        if not text:
            self._err(v, f"{kind} {v['name']!r} has no description string")
        return unit, text

    def _parameter(self, b: BlockBuilder, k: int) -> None:
        v = self.vars[k]
        a = v["attributes"]
        node = a.get("binding") if a.get("binding") is not None else a.get("start")
        if node is None:
            self._err(v, f"parameter {v['name']!r} has no value")
        value = self.graph(node)
        if not value.is_constant():  # a parameter computed from others: not settable
            self.env[("parameter", k)] = value
            return
        unit, text = self._doc(v, "parameter")
        lo, hi = self._constant(a.get("min"), v, "min"), self._constant(a.get("max"), v, "max")
        default = float(ca.evalf(value))
        self.env[("parameter", k)] = b.param(v["name"], default, unit, text,
                                             lower=-math.inf if lo is None else lo, upper=math.inf if hi is None else hi)

    def _refuse_flat(self) -> None:
        """What the token scan cannot see (e.g. a construct reached through an extends)."""
        for key, what in (("algorithms", "an algorithm section"), ("when_chains", "a when-equation"),
                          ("initial_equations", "an initial equation"), ("assert_equations", "an assert"),
                          ("functions", "a function")):
            if self.flat.get(key):
                raise ModelicaError(self.filename, None, f"the model contains {what}, which is not supported")
        if self.st.get("discrete_real_equations") or self.st.get("time_events") or self.st.get("delays"):
            raise ModelicaError(self.filename, None, "the model has events or delays, which are not supported")

    def _residuals(self) -> list[tuple[ca.SX, int | None]]:
        out = []
        for op in self.st["continuous_equation_operations"]:
            (kind, body), = op.items()
            origin = (body.get("provenance") or {}).get("origin")
            if isinstance(origin, dict) and origin.get("generated") == "flow_balance_equation":
                continue  # "flow = 0" of an unconnected top-level connector: here a flange bonds it
            span = (body.get("provenance") or {}).get("span") or {}
            line = self._offset_line(span.get("start"))
            if kind != "residual":
                raise ModelicaError(self.filename, line, f"an equation of kind {kind!r} is not supported")
            self.units(body["residual"])  # raises at a unit mismatch
            e = self.graph(body["residual"])
            if e.numel() != 1:
                raise ModelicaError(self.filename, line, "array equations are not supported (write scalars)")
            out.append((e, line))
        return out

    # connectors
    def _connectors(self) -> list[dict]:
        """``[{name, potential, flow}]`` (DAE variable indices) of the top-level connectors."""
        flat_vars = self.flat["variables"]
        index = {v["name"]: k for k, v in enumerate(self.vars)}
        out = []
        for conn in self.flat.get("top_level_connectors", []):
            members = [n for n in flat_vars if n.startswith(conn + ".") or n.startswith(conn + "[")]
            if "[" in conn or any(n[len(conn)] == "[" for n in members):
                self._err(self.vars[index[members[0]]] if members else None,
                          f"{conn}: arrays of connectors are not supported")
            flows = [n for n in members if flat_vars[n]["flow"]]
            pots = [n for n in members if not flat_vars[n]["flow"]]
            if len(flows) != 1 or len(pots) != 1:
                self._err(self.vars[index[members[0]]] if members else None,
                          f"connector {conn} has {len(pots)} potential and {len(flows)} flow variables; a flange "
                          f"needs one of each (e.g. Real v(unit = \"m/s\"); flow Real f(unit = \"N\"))")
            p, f = self.vars[index[pots[0]]], self.vars[index[flows[0]]]
            unit = p["attributes"].get("unit") or ""
            if unit not in _POSITION_UNITS + _VELOCITY_UNITS:
                self._err(p, f"connector {conn}: its potential {pots[0]} has unit {unit!r}; a flange's potential is a "
                             f"velocity (m/s, rad/s) or a position (m, rad)")
            out.append({"name": conn, "potential": index[pots[0]], "flow": index[flows[0]],
                        "position": unit in _POSITION_UNITS})
        return out

    def _solve(self, b: BlockBuilder, residuals, unknown: dict, flanges: list[dict]):
        """Choose each flange's causality so that the equations determine the unknowns; returns
        the solved unknowns (key -> expression) and the choice per flange."""
        res = ca.vertcat(*[r for r, _ in residuals]) if residuals else ca.SX(0, 1)
        options = []
        for fl in flanges:  # effort_out: the potential is given (an input); flow_out: the flow is given
            options.append([("effort_out", ("algebraic", fl["potential"])), ("flow_out", ("algebraic", fl["flow"]))])
        for choice in product(*options) if flanges else [()]:
            given = {key for _, key in choice}
            keys = [k for k in unknown if k not in given]
            if len(keys) != res.numel():
                continue
            w = ca.vertcat(*[unknown[k] for k in keys]) if keys else ca.SX(0, 1)
            if keys and ca.sprank(ca.jacobian_sparsity(res, w)) < len(keys):
                continue
            subst = self._inputs_for(b, flanges, choice, unknown)
            r = ca.substitute(res, ca.vertcat(*subst.keys()), ca.vertcat(*subst.values())) if subst else res
            return self._sorted_solve(r, keys, unknown, residuals), choice
        n_eq = res.numel()
        raise ModelicaError(self.filename, None, f"the equations do not determine the model's variables: {n_eq} "
                                                 f"equations for {len(unknown) - len(flanges)} unknowns (states' "
                                                 f"derivatives, outputs and other variables; connectors counted with "
                                                 f"one of their two variables given)")

    def _inputs_for(self, b: BlockBuilder, flanges, choice, unknown) -> dict:
        """Declare each flange's given variable as an input; returns symbol -> its expression."""
        subst = {}
        for fl, (causality, key) in zip(flanges, choice):
            v = self.vars[key[1]]
            if causality == "effort_out":
                unit, text = self._doc(v, "connector variable")
                if fl["position"]:  # our flange carries the rate: the position is a state
                    vel = b.input(f"{fl['name']}.v", "m/s" if unit == "m" else "rad/s", f"rate of {text}")
                    start = v["attributes"].get("start")
                    pos = b.state(f"state.{v['name']}", self.graph(start) if start is not None else 0.0, unit, text)
                    b.der(pos, vel)
                    subst[unknown[key]] = pos
                    fl["rate"] = vel
                else:
                    subst[unknown[key]] = b.input(v["name"], unit, text)
            else:
                unit, text = self._doc(v, "connector variable")
                subst[unknown[key]] = b.input(v["name"], unit, text)
            self.env[key] = subst[unknown[key]]
        return subst

    def _sorted_solve(self, res: ca.SX, keys: list, unknown: dict, residuals) -> dict:
        """Solve ``res(w) = 0`` for the unknowns ``keys``: equations linear in a single unknown
        first, then the remaining coupled block (linear: a symbolic sparse solve; nonlinear:
        unrolled Newton from 0)."""
        rows = [res[i] for i in range(res.numel())]
        lines = [line for _, line in residuals]
        pending = {k: unknown[k] for k in keys}
        solved: dict = {}
        progress = True
        while pending and progress:
            progress = False
            for i, r in enumerate(rows):
                if r is None:
                    continue
                deps = [k for k, s in pending.items() if ca.depends_on(r, s)]
                if not deps:
                    if not r.is_zero():
                        raise ModelicaError(self.filename, lines[i], "this equation is redundant or "
                                                                     "contradicts the others")
                    rows[i] = None
                    continue
                if len(deps) != 1:
                    continue
                s = pending[deps[0]]
                coef = ca.jacobian(r, s)
                if ca.depends_on(coef, s):
                    continue
                value = -ca.substitute(r, s, ca.SX(0)) / coef
                solved[deps[0]] = value
                del pending[deps[0]]
                rows = [None if (j == i or q is None) else ca.substitute(q, s, value) for j, q in enumerate(rows)]
                solved = {k: ca.substitute(v, s, value) for k, v in solved.items()}
                progress = True
                break
        if pending:
            left = [r for r in rows if r is not None]
            R = ca.vertcat(*left)
            Z = ca.vertcat(*pending.values())
            J = ca.jacobian(R, Z)
            if not ca.depends_on(J, Z):
                sol = ca.solve(J, -ca.substitute(R, Z, ca.SX.zeros(Z.shape)))
            else:  # Newton from 0; a loop it does not close gives NaN, which stops the run (not a wrong value)
                sol = ca.SX.zeros(Z.shape)
                for _ in range(NEWTON_ITERATIONS):
                    sol = sol - ca.solve(ca.substitute(J, Z, sol), ca.substitute(R, Z, sol))
                size = ca.norm_inf(sol)
                closed = ca.logic_and(size < ca.inf, ca.norm_inf(ca.substitute(R, Z, sol)) <= NEWTON_TOL * (1 + size))
                sol = ca.if_else(closed, sol, ca.SX.nan(Z.shape))
            for j, k in enumerate(pending):
                solved[k] = sol[j]
            solved = {k: ca.substitute(v, Z, sol) for k, v in solved.items()}
        return solved

    def _flange(self, b: BlockBuilder, fl: dict, causality: str, value: dict) -> None:
        pv, fv = self.vars[fl["potential"]], self.vars[fl["flow"]]
        name = fl["name"]
        if causality == "effort_out":  # potential in, effort (force on the partner = -f) out
            unit, text = self._doc(fv, "connector variable")
            b.output(fv["name"], -value[fl["flow"]], unit, f"on the partner: -{fv['name']} of the model, whose flow "
                                                           f"variable is the {text}")
            flow = f"{name}.v" if fl["position"] else pv["name"]
            b.flange(name, fv["name"], flow, "effort_out")
        else:  # effort in, potential (or its rate) out
            unit, text = self._doc(pv, "connector variable")
            if fl["position"]:
                s = value[fl["potential"]]
                xs = ca.vertcat(*[sym for _, sym, _ in b._states]) if b._states else ca.SX(0, 1)
                us = ca.vertcat(*[sym for _, sym in b._inputs]) if b._inputs else ca.SX(0, 1)
                if us.numel() and ca.depends_on(s, us):
                    self._err(pv, f"{pv['name']}: a position flange's position may depend on states only")
                rate = ca.jtimes(s, xs, ca.vertcat(*[b._ders[v.name] for v, _, _ in b._states])) if b._states \
                    else ca.SX(0.0)
                b.output(f"{name}.v", rate, "m/s" if unit == "m" else "rad/s", f"rate of {text}")
                b.output(pv["name"], s, unit, text)
                b.flange(name, fv["name"], f"{name}.v", "flow_out")
            else:
                b.output(pv["name"], value[fl["potential"]], unit, text)
                b.flange(name, fv["name"], pv["name"], "flow_out")


__all__ = ["translate", "unsupported", "ModelicaError", "DAE_SCHEMA", "INTEGRATORS"]
