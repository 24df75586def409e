"""Modelica models as blocks: a ``.mo`` text translated into a :class:`~models.block.Block`.

The front end is `rumoca <https://pypi.org/project/rumoca/>`_ (a Modelica compiler written in
Rust with a Python API; no OpenModelica needed): it parses, resolves, flattens and checks the
model and hands over its DAE as an expression graph (``Model.to_dict("dae")``), which this module
turns into CasADi SX.  rumoca's own ``casadi-ode`` target is not used because it refuses models
whose outputs are algebraic equations; its FMU targets are not used because the FMU is built by
our exporter (:mod:`fmus`: our integrators, our C core, strict FMI).

What a model may contain (anything else is refused with ``file:line: construct``):

- ``parameter Real`` with a value (a number, or an expression of other parameters: then it is
  computed, not settable); ``min``/``max`` become bounds;
- ``input Real`` / ``output Real``.  Units and description strings are optional, as in Modelica:
  a variable without a unit is exported with none (unknown; a wildcard in the unit check), a
  unit this module cannot read is exported with none too, and the description says which;
- continuous ``Real`` variables; those that appear in ``der()`` are states (start value from
  ``start``, a number or an expression of parameters; exported as ``state.<name>``);
- equations (acausal: the residuals are sorted and solved symbolically: one unknown at a time
  where an equation is linear in it, a linear algebraic loop by a symbolic sparse solve, a
  nonlinear one by Newton iterations unrolled into the generated code);
- classes of other files and libraries (``extends``, ``import``), which rumoca reads from the
  source ``roots`` its caller gives (:mod:`cosim.scenario.modelica_sources` chooses the files);
- Boolean, Integer and enumeration parameters and constants (fixed: they select equations);
- every other variable (algebraic, states, inner components' outputs) exported as an FMI local
  under its Modelica name, so it can be recorded;
- states tied by a constraint (index 2): one of them is computed from the constraint and its
  time derivative is added (:meth:`_Translation._reduce_index`);
- the built-in functions sin, cos, tan, asin, acos, atan, atan2, sinh, cosh, tanh, exp, log,
  log10, sqrt, abs, sign, min, max, floor, ceil, smooth, noEvent, homotopy and if-expressions;
  functions whose algorithm is a sequence of assignments (inlined);
- ``time`` (the block's event time in indicators and updates; a clock state where the continuous
  equations read it);
- events (docs/explanation/events.md): discrete Real variables are modes (``pre`` their left
  value); ``when`` on a relation is an indicator with its update (``reinit`` and the clause's
  discrete equations); a relation on states, inputs or variables read by the continuous
  equations (outside ``noEvent``) is a state event: an indicator and a mode holding its truth,
  which the equations read (:meth:`_Translation._frozen_relations`);
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

Also taken: initial equations and ``fixed = true`` (:meth:`_Translation._initial`), Boolean and
Integer variables of always-active equations (modes settled after every event), relations on
time as time events, ``when sample(start, interval)`` as periodic time events, ``when
initial()`` as a time event at the start, ``edge(b)``/``change(b)`` of a Boolean given by a
relation (that relation's indicator), Boolean and Integer variables assigned in a when-clause
(modes, like a discrete Real), ``elsewhen`` chains of relations (each condition's truth a mode;
the first branch whose condition becomes true wins), arrays (vectors and matrices: one variable
per element, ``x[2]``, ``A[1,2]``) with for-equations and array equations over them, functions
whose for-loops and if-statements rumoca lowers into assignments, a model's algorithm section
with one output (rumoca lowers it into an equation), asserts on parameters (checked at their
values) and on variables (a latched mode each; at level error rated, so the run-time guard ends
the run quoting the assertion).

Refused: algorithm sections of several outputs (rumoca's refusal, with the section's line),
statements rumoca does not lower in functions, external functions, initial algorithms that set
other than discrete variables, terminate, ``edge``/``change`` of anything else, an ``elsewhen`` branch on anything but a
relation, arrays of more than two dimensions, colon subscripts (``A[:, 2]``), ``delay``, String
variables, inner/outer, stream connectors, arrays of connectors.

``models/`` is maths only: :func:`translate` takes the model's text (and rumoca reads the roots
it is given); choosing and reading files is the caller's (:mod:`cosim.scenario`).
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from itertools import product

import casadi as ca
import numpy as np

from . import units
from .block import EITHER, FALLING, RISING, Block, BlockError, Sample, Var
from .user import BlockBuilder

#: The rumoca DAE schema this translator reads (``Model.to_dict("dae")["schema_version"]``).
DAE_SCHEMA = 43
#: Newton iterations unrolled into the code for a nonlinear algebraic loop.
NEWTON_ITERATIONS = 12
#: A nonlinear loop is closed when its residual is below this, relative to ``1 + |z|``.
NEWTON_TOL = 1e-10
INTEGRATORS = ("auto", "exact", "rk4", "radau")
#: The period of a time event that fires once (a Sample's period must be finite).
ONCE = 1e300


class ModelicaError(BlockError):
    """A model the translation cannot take: ``str()`` is ``file:line: what``."""

    def __init__(self, filename: str, line: int | None, message: str):
        self.filename, self.line, self.message = filename, line, message
        super().__init__(f"{filename}:{line}: {message}" if line else f"{filename}: {message}")


# --- what is refused, found in the text ----------------------------------------------------------
_UNSUPPORTED = {
    "external": "external functions are not supported",
    "terminate": "terminate() is not supported",
    "delay": "delay() is not supported",
    "String": "String variables are not supported (Real, and Integer/Boolean parameters)",
    "inner": "inner/outer is not supported", "outer": "inner/outer is not supported",
    "stream": "stream connectors are not supported",
}
_TOKEN = re.compile(r'//[^\n]*|/\*.*?\*/|"(?:\\.|[^"\\])*"|[A-Za-z_][A-Za-z0-9_]*|\S', re.S)


def _tokens(text: str):
    """``(token, line)`` of the identifiers and symbols of ``text`` (comments and strings skipped)."""
    for m in _TOKEN.finditer(text):
        tok = m.group(0)
        if tok.startswith(("//", "/*", '"')):
            continue
        yield tok, text.count("\n", 0, m.start()) + 1


def _a_name(toks: list) -> bool:
    """Whether ``toks`` start with ``( name )`` (a dotted component reference)."""
    if not toks or toks[0][0] != "(":
        return False
    for j, (tok, _) in enumerate(toks[1:], 1):
        if tok == ")":
            return j > 1
        if tok != "." and not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", tok):
            return False
    return False


def unsupported(text: str, filename: str) -> None:
    """Raise :class:`ModelicaError` at the first construct the translation refuses."""
    toks = list(_tokens(text))
    functions: list[str] = []  # the function definitions being read (their algorithms are taken)
    for k, (tok, line) in enumerate(toks):
        prev = toks[k - 1][0] if k else ""
        if tok == "function" and prev != "end" and k + 1 < len(toks):
            functions.append(toks[k + 1][0])
        elif prev == "end" and functions and tok == functions[-1]:
            functions.pop()
        if tok in ("edge", "change") and prev != "." and not _a_name(toks[k + 1:]):
            raise ModelicaError(filename, line, f"{tok}: {tok}() of an expression is not supported ({tok}(b) of a "
                                                f"Boolean variable b given by a relation is)")
        if tok in _UNSUPPORTED:
            if prev == ".":  # a component's member named like a keyword-free builtin (a.time)
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


def _compile(text: str, model: str, filename: str, roots: tuple[str, ...] = ()):
    """rumoca's model of ``text`` (:class:`ModelicaError` with the line of a front-end error).

    ``roots`` are the source roots rumoca may read (directories laid out as Modelica packages);
    ``text`` is given under the name ``<filename>``, which is no path, so rumoca reads no file
    beside it (a real path makes it load every ``.mo`` of that directory)."""
    try:
        import rumoca
    except ModuleNotFoundError:
        raise ModelicaError(filename, None, "Modelica components need the rumoca front end: pip install "
                                            "rumoca (the project's dependencies include it)") from None
    virtual = f"<{filename}>"
    try:
        return rumoca.Session(roots=list(roots)).loads(text, model=model, filename=virtual)
    except rumoca.RumocaError as exc:
        msg = str(exc).replace(virtual, filename)
        first = msg.splitlines()[0] if msg else type(exc).__name__
        first = re.sub(r"^\S+ could not be compiled: ", "", first)
        loc = _LOCATION.search(msg)
        where = filename
        line = int(loc.group(2)) if loc else None
        if loc and loc.group(1) not in (filename, virtual):
            where = loc.group(1)  # in a library file
        if line is None and not roots:  # the compiler's summary has no location: its diagnostics do
            for d in rumoca.validate_source(text, model=model, filename=virtual):
                found = _LOCATION.search(d.message or "")
                if d.level == "error" and found:
                    line = int(found.group(2))
                    break
        for d in getattr(exc, "diagnostics", []) or []:
            if line is None and d.line and d.line > 1:
                line = d.line
        if line is None and "algorithm" in msg:  # rumoca's refusal of a model's algorithm names no line
            line = _first_line(text, "algorithm")
            first = f"algorithm: {first}"
        if line is None:
            unresolved = _UNRESOLVED.search(msg)
            if unresolved:
                line = _first_line(text, unresolved.group(1))
        if line is None and model and model not in _classes(text) and model.split(".")[-1] not in _classes(text):
            first = f"{first} (the file defines {', '.join(_classes(text)) or 'no class'})"
        raise ModelicaError(where, line, first.strip().rstrip(":")) from None


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


_FRONT_END: dict[tuple[str, str, str], dict] = {}  # (sha256, model, file) -> result


def front_end(text: str, model: str, filename: str = "model.mo", roots: tuple[str, ...] = ()) -> dict:
    """What rumoca compiles of class ``model`` of ``text`` with the source ``roots``: ``{"name",
    "dae", "flat"}`` (plain data: JSON-able, so a caller may cache it), compiled in a forked child
    so that a crash of the compiler (a signal) is one :class:`ModelicaError`, not the death of the
    workbench.  rumoca is imported once in this process (the child inherits it); the result of a
    text without roots is kept per source, model and file name, so a second component of the
    same class compiles nothing (with roots, the caller keys the files it gives:
    :mod:`cosim.scenario.modelica_sources`)."""
    import hashlib
    import os
    import pickle
    import signal

    roots = tuple(str(r) for r in roots)
    key = (hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest(), model, filename)
    if not roots and key in _FRONT_END:
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
                m = _compile(text, model, filename, roots)
                out = ("ok", {"name": m.name, "dae": m.to_dict("dae"), "flat": m.to_dict("flat")})
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
    try:
        kind, payload = pickle.loads(data)
    except (pickle.UnpicklingError, EOFError, ValueError):
        raise ModelicaError(filename, None, f"the Modelica front end (rumoca) gave no readable result for {model} "
                                            f"(exit {os.waitstatus_to_exitcode(status)})") from None
    if kind == "error":
        raise ModelicaError(*payload)
    dae = payload["dae"]
    if dae.get("schema_version") != DAE_SCHEMA:
        raise ModelicaError(filename, None, f"rumoca {_rumoca_version()} writes DAE schema "
                                            f"{dae.get('schema_version')}; this translator reads schema {DAE_SCHEMA} "
                                            f"(rumoca 0.10.x)")
    if not roots:
        _FRONT_END[key] = payload
    return payload


def _classes(text: str) -> list[str]:
    toks = [t for t, _ in _tokens(text)]
    return [toks[i + 1] for i, t in enumerate(toks[:-1])
            if t in ("model", "block", "class", "package") and (i == 0 or toks[i - 1] != "end")]


# --- the DAE expression graph as CasADi -----------------------------------------------------------
def _times(a: ca.SX, b: ca.SX) -> ca.SX:
    """Modelica's ``*``: a scalar scales; vector * vector is the dot product, matrix * vector,
    vector * matrix and matrix * matrix the matrix products (vectors are columns here)."""
    if a.numel() == 1 or b.numel() == 1:
        return a * b
    if a.shape[1] == 1 and b.shape[1] == 1:
        return ca.dot(a, b)
    if a.shape[1] == 1:
        return ca.mtimes(a.T, b).T
    return ca.mtimes(a, b)


_BINARY = {
    "add": lambda a, b: a + b, "subtract": lambda a, b: a - b, "multiply": _times,
    "divide": lambda a, b: a / b, "power": lambda a, b: a ** b,
    "elementwise_add": lambda a, b: a + b, "elementwise_subtract": lambda a, b: a - b,
    "elementwise_multiply": lambda a, b: a * b, "elementwise_divide": lambda a, b: a / b,
    "elementwise_power": lambda a, b: a ** b,
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
    "integer": ca.floor, "mod": lambda a, b: a - ca.floor(a / b) * b, "div": lambda a, b: ca.sign(a / b) * ca.floor(ca.fabs(a / b)),
    "rem": lambda a, b: a - ca.sign(a / b) * ca.floor(ca.fabs(a / b)) * b,
    "smooth": lambda order, a: a, "no_event": lambda a: a, "homotopy": lambda actual, simplified: actual,
}

#: Array built-in functions (vectors are SX columns, matrices SX matrices; at most two dimensions).
_ARRAY_BUILTINS = ("ones", "zeros", "fill", "sum", "product", "scalar", "vector", "size", "promoted_cat1",
                   "promoted_cat2", "cat", "transpose", "identity", "diagonal", "cross", "linspace", "ndims",
                   "outer_product")


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

    functions: list = dataclasses.field(default_factory=list)  # the DAE's functions (inlined at calls)
    domains: list = dataclasses.field(default_factory=list)  # the DAE's index domains (for-loops, comprehensions)
    structural: object = None  # e -> e at the parameters' values (an array size is fixed when translated)

    def __post_init__(self):
        self.memo: dict[int, ca.SX] = {}
        self.inlined: dict[tuple[int, int], tuple[list[ca.SX], ca.SX]] = {}  # (function, output) -> (params, body)

    def __call__(self, i: int) -> ca.SX:
        hit = self.memo.get(i)
        if hit is None:
            hit = self.memo[i] = self._eval(i)
        return hit

    def _eval(self, i: int) -> ca.SX:
        (kind, body), = self.nodes[i].items()
        if kind == "literal":
            (t, v), = body.items()
            if t == "boolean":
                return ca.SX(1.0 if v else 0.0)
            if t not in ("real", "integer", "enumeration"):  # an enumeration literal is its ordinal
                self._refuse(i, f"a {t} literal is not supported (Real, Integer, Boolean and enumerations only)")
            return ca.SX(float(v))
        if kind == "coordinate":
            key = ("time", 0) if body == "time" else next(iter(body.items()))
            if key[0] == "function_parameter":
                key = ("function_parameter", (key[1]["function"], key[1]["ordinal"]))
            elif key[0] == "binder":
                key = ("binder", (key[1]["domain"], key[1]["ordinal"]))
            elif key[0] == "function_variable" and isinstance(key[1], dict):
                key = ("function_variable", (key[1].get("function"), key[1].get("ordinal")))
            if key not in self.env:
                self._refuse(i, f"{key[0].replace('_', ' ')} is not supported here")
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
        if kind == "builtin" and body["builtin"] in _ARRAY_BUILTINS:
            return self._array_builtin(i, body["builtin"], args)
        if kind == "builtin" and body["builtin"] in ("min", "max") and len(args) == 1:
            return (ca.mmin if body["builtin"] == "min" else ca.mmax)(args[0])  # min/max of an array
        if kind == "builtin":
            fn = _BUILTIN.get(body["builtin"])
            if fn is None:
                self._refuse(i, f"the function {body['builtin']}() is not supported")
            return fn(*args)
        if kind == "array":  # {a, b, c}: a column; {{..}, {..}}: a matrix, one row per element
            if all(a.numel() == 1 for a in args):
                return ca.vertcat(*args)
            if all(a.shape == args[0].shape and a.shape[1] == 1 for a in args):
                return ca.horzcat(*args).T
            self._refuse(i, "an array of more than two dimensions is not supported")
        if kind == "index":
            return self._index(i, self(body["base"]), [self(n) for n in self._subscripts(i, body)])
        if kind == "runtime_quotient_owner":  # mod(), div(), rem() (integer division)
            a, b = self(body["lhs"]), self(body["rhs"])
            q = ca.sign(a / b) * ca.floor(ca.fabs(a / b))  # div: truncated towards zero
            ops = {"mod": lambda: a - ca.floor(a / b) * b, "div": lambda: q, "rem": lambda: a - q * b}
            if body.get("builtin") not in ops:
                self._refuse(i, f"the function {body.get('builtin')}() is not supported")
            return ops[body["builtin"]]()
        if kind == "range":  # start:step:stop of constants: a column
            ends = [self(body[k]) if body.get(k) is not None else ca.SX(1.0)
                    for k in ("start_expression", "explicit_step_expression", "stop_expression")]
            if not all(e.is_constant() for e in ends):
                self._refuse(i, "a range whose bounds are not constants is not supported")
            a, h, b = (float(ca.evalf(e)) for e in ends)
            n = int(math.floor((b - a) / h + 1e-9)) + 1 if h else 0
            return ca.vertcat(*[ca.SX(a + h * k) for k in range(max(n, 0))]) if n > 0 else ca.SX(0, 1)
        if kind == "function_value":  # a function variable as its definition_ordinal-th assignment left it
            key = ("function_value", (body["function"], body["value"], body["definition_ordinal"]))
            if key not in self.env:
                self._refuse(i, "a function variable read before it is assigned")
            return self.env[key]
        if kind == "comprehension":  # {body for i in lo:hi}: a column of the body at each binder value
            dom = self.domains[body["domain"]]["domain"]["binders"]
            if len(dom) != 1:
                self._refuse(i, "a comprehension over more than one index is not supported")
            bd = dom[0]
            out = []
            for v in range(bd["lower"], bd["upper"] + 1, bd.get("step") or 1):
                g = dataclasses.replace(self, env={**self.env, ("binder", (body["domain"], 0)): ca.SX(float(v))})
                out.append(g(body["body"]))
            return ca.vertcat(*out)
        if kind == "conditional":  # (c1, v1, c2, v2, ..., else)
            value = args[-1]
            for k in range(len(args) - 3, -1, -2):
                value = ca.if_else(args[k], args[k + 1], value)
            return value
        if kind == "call" and body.get("derivative") is None:
            params, out = self._inline(i, body["function"], body.get("output", 0), tuple(a.shape for a in args))
            if len(params) != len(args):
                self._refuse(i, f"a call of {self.functions[body['function']]['name']} with {len(args)} arguments "
                                f"(it takes {len(params)})")
            return ca.substitute(out, ca.vertcat(*[ca.vec(p) for p in params]),
                                 ca.vertcat(*[ca.vec(a) for a in args])) if params else out
        self._refuse(i, f"the expression kind {kind!r} is not supported")

    def _subtree_start(self, j: int) -> int:
        """The first node of node ``j``'s subtree (the nodes are stored children first)."""
        (kind, body), = self.nodes[j].items()
        kids = []
        if kind == "binary":
            kids = [body["lhs"], body["rhs"]]
        elif kind == "unary":
            kids = [body["operand"]]
        elif kind == "index":
            kids = [body["base"]]
        elif kind == "runtime_quotient_owner":
            kids = [body["lhs"], body["rhs"]]
        elif kind == "range":
            kids = [body[k] for k in ("start_expression", "explicit_step_expression", "stop_expression")
                    if body.get(k) is not None]
        elif isinstance(body, dict) and body.get("operand_count"):
            kids = [self.operands[self.starts[j] + k] for k in range(body["operand_count"])]
        return min([j] + [self._subtree_start(c) for c in kids])

    def _subscripts(self, i: int, body: dict) -> list[int]:
        """The subscript nodes of index node ``i``: the subtrees between its base and itself."""
        roots, j = [], i - 1
        for _ in range(body.get("subscript_count", 0)):
            roots.append(j)
            j = self._subtree_start(j) - 1
        if j != body["base"]:
            self._refuse(i, "a subscript of a form not understood here (a constant or a for-loop index expected)")
        return roots[::-1]

    def _index(self, i: int, base: ca.SX, subs: list[ca.SX]) -> ca.SX:
        """``base[subs]`` (1-based constant subscripts; one subscript of a matrix is its row)."""
        idx = []
        for s in subs:
            if not s.is_constant():
                self._refuse(i, "a subscript that is not a constant or a for-loop index is not supported")
            idx.append(int(round(float(ca.evalf(s)))) - 1 if s.numel() == 1 else
                       [int(round(v)) - 1 for v in np.asarray(ca.evalf(s)).ravel()])
        if any(isinstance(k, list) for k in idx):  # a range subscript: the elements it selects
            shape = [base.shape[0]] if base.shape[1] == 1 else list(base.shape)
            lists = [k if isinstance(k, list) else [k] for k in idx]
            if len(lists) != len(shape) or any(not 0 <= k < n for ks, n in zip(lists, shape) for k in ks):
                self._refuse(i, "a range subscript out of the array's range")
            if len(shape) == 1:
                return ca.vertcat(*[base[k] for k in lists[0]])
            out = ca.vertcat(*[ca.horzcat(*[base[r, c] for c in lists[1]]) for r in lists[0]])
            return out if len(lists[0]) > 1 and len(lists[1]) > 1 else ca.vec(out)
        if base.numel() == 1 and all(k == 0 for k in idx):
            return base  # a one-element array is its element
        shape = [base.shape[0]] if base.shape[1] == 1 else ([base.shape[1]] if base.shape[0] == 1 else list(base.shape))
        if len(idx) > len(shape) or any(not 0 <= k < n for k, n in zip(idx, shape)):
            self._refuse(i, f"subscript [{', '.join(str(k + 1) for k in idx)}] out of the array's range "
                            f"[{', '.join(map(str, shape))}]")
        if len(shape) == 1:
            return base[idx[0]]
        if len(idx) == 1:
            return base[idx[0], :].T
        return base[idx[0], idx[1]]

    def _array_builtin(self, i: int, name: str, args: list[ca.SX]) -> ca.SX:
        """The array built-in functions on SX columns (vectors) and matrices."""
        def count(n: ca.SX) -> int:
            if not n.is_constant() and self.structural is not None:
                n = self.structural(n)
            if not n.is_constant():
                self._refuse(i, f"{name}(): a size that is not a constant")
            return int(round(float(ca.evalf(n))))

        if name in ("ones", "zeros", "fill"):
            sizes = [count(n) for n in (args if name != "fill" else args[1:])]
            if len(sizes) > 2:
                self._refuse(i, f"{name}() of more than two dimensions is not supported")
            shape = (sizes + [1])[:2]
            value = {"ones": ca.SX(1.0), "zeros": ca.SX(0.0)}.get(name, args[0] if args else ca.SX(0.0))
            return ca.repmat(value, *shape) if value.numel() == 1 else self._refuse(i, "fill() of an array")
        if name == "size":
            a = args[0]
            shape = [a.shape[0]] if a.shape[1] == 1 else list(a.shape)
            if len(args) == 1:
                return ca.vertcat(*[ca.SX(float(n)) for n in shape]) if len(shape) > 1 else ca.SX(float(shape[0]))
            d = count(args[1])
            return ca.SX(float(shape[d - 1] if d <= len(shape) else 1))
        if name == "ndims":
            return ca.SX(1.0 if args[0].shape[1] == 1 else 2.0)
        if name == "promoted_cat1":
            return ca.vertcat(*args)
        if name == "promoted_cat2":
            return ca.horzcat(*args)
        if name == "cat":
            d = count(args[0])
            return ca.vertcat(*args[1:]) if d == 1 else ca.horzcat(*args[1:])
        if name == "transpose":
            return args[0].T
        if name == "identity":
            return ca.SX.eye(count(args[0]))
        if name == "diagonal":
            return ca.diag(args[0])
        if name == "cross":
            return ca.cross(args[0], args[1])
        if name == "outer_product":
            return ca.mtimes(args[0], args[1].T)
        if name == "linspace":
            n = count(args[2])
            return ca.vertcat(*[args[0] + (args[1] - args[0]) * k / (n - 1) for k in range(n)])
        if len(args) != 1:
            self._refuse(i, f"{name}() of {len(args)} arguments is not supported")
        a = args[0]
        if name == "sum":
            return ca.sum1(ca.sum2(a))
        if name == "product":
            out = ca.SX(1.0)
            for k in range(a.numel()):
                out = out * a[k]
            return out
        if name == "scalar":
            return a[0]
        return ca.vec(a.T)  # vector(): the elements in row-major order, a column

    def _inline(self, i: int, f: int, output: int, shapes: tuple = ()) -> tuple[list[ca.SX], ca.SX]:
        """Output ``output`` of the DAE's function ``f`` as an expression of its parameters'
        symbols (shaped as the call's arguments, ``shapes``): its algorithm (assignments in
        order) evaluated symbolically."""
        key = (f, output, shapes)
        if key in self.inlined:
            return self.inlined[key]
        fn = self.functions[f]
        if fn.get("external") is not None:
            self._refuse(i, f"{fn['name']} is an external function, which is not supported")
        params = [ca.SX.sym(f"{fn['name']}.{p['name']}", *(shapes[k] if k < len(shapes) else (1, 1)))
                  for k, p in enumerate(fn["parameters"])]
        names = [v["name"] for v in fn["outputs"] + fn.get("locals", [])]
        values: list[ca.SX | None] = [None] * len(names)
        env = dict(self.env)
        env.update({("function_parameter", (f, k)): s for k, s in enumerate(params)})
        count = 0  # the assignments made so far: a read names its definition by this ordinal
        for stmt in fn.get("statements", []):
            (skind, sbody), = stmt.items()
            if skind == "assignment":
                group = [sbody]
            elif skind == "assignment_group":  # an if-statement rumoca lowered: each target an if-expression
                group = sbody.get("assignments", [])
            else:
                self._refuse(i, f"{fn['name']}: a {skind.replace('_', ' ')} statement in its algorithm is not "
                                f"supported (assignments, for-loops and if-statements rumoca lowers into them)")
            sub = dataclasses.replace(self, env={**env, **{("function_variable", (f, k)): v
                                                            for k, v in enumerate(values) if v is not None}})
            new = [(a["target"], sub(a["rhs"])) for a in group]
            for target, value in new:
                values[target] = env[("function_value", (f, target, count))] = value
                count += 1
        if values[output] is None:
            self._refuse(i, f"{fn['name']}: its output {names[output]} is never assigned")
        self.inlined[key] = (params, values[output])
        return self.inlined[key]

    def _refuse(self, i: int, what: str):
        raise ModelicaError(self.filename, self.line_of(i), what)


_SAME = ("add", "subtract", "greater", "less", "greater_equal", "less_equal", "greater_or_equal",
         "less_or_equal", "equal", "not_equal")
_DIMENSIONLESS_ARG = ("sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh", "exp", "log", "log10")


class _Units:
    """The unit check of the DAE's expressions: every sum, comparison, min/max and branch of an
    if-expression must add like units, and the built-in functions' arguments be dimensionless.
    A variable without a unit (or with a symbol :mod:`models.units` does not know) and a number
    in a sum are wildcards; a number in a product is a dimensionless factor.  ``time`` is in
    seconds where the model declares a unit anywhere; in a model that declares none (units are
    optional) it is a wildcard too, so ``sin(time)`` is not refused for a unit nobody wrote."""

    def __init__(self, graph: _Graph, var_units: dict[int, str]):
        self.g = graph
        self.units = {k: units.parse(u) for k, u in var_units.items()}
        self.declared = var_units
        self.time = units.parse("s") if any(var_units.values()) else None
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
            if body == "time":
                return self.time, False, "time [s]" if self.time is not None else "time"
            (what, k), = body.items()
            if what not in ("parameter", "input", "output", "state", "derivative", "algebraic"):
                return None, False, "?"
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
            if name in ("min", "max") and len(args) == 1:
                return args[0]
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


_REL = {"less": "<", "less_equal": "<=", "greater": ">", "greater_equal": ">="}


def _find(tree, key: str) -> list[dict]:
    """Every value under ``key`` in the nested dicts and lists ``tree`` (rumoca's flat model)."""
    if isinstance(tree, dict):
        return ([tree[key]] if key in tree else []) + [f for v in tree.values() for f in _find(v, key)]
    if isinstance(tree, list):
        return [f for v in tree for f in _find(v, key)]
    return []


def _elements(e: ca.SX) -> list[ca.SX]:
    """The elements of an array expression in row-major order (a scalar: itself)."""
    return [e[r, c] for r in range(e.shape[0]) for c in range(e.shape[1])]


def _short(e: ca.SX, limit: int = 120) -> str:
    text = str(ca.simplify(e))
    return text if len(text) <= limit else text[:limit] + "..."


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


def refuse_unsupported(text: str, filename: str) -> None:
    """The text checks :func:`translate` makes first (a caller that compiles before translating
    makes them before compiling, so a refused construct is named by its line, not by rumoca)."""
    bounded(text, filename)
    unsupported(text, filename)


#: A flange's causality: ``effort_out`` computes the force from the partner's velocity,
#: ``flow_out`` the velocity from the partner's force.
CAUSALITIES = ("effort_out", "flow_out")


def translate(text: str, model: str, filename: str = "model.mo", *, name: str | None = None,
              integrator: str = "auto", substeps: int = 1, roots: tuple[str, ...] = (),
              compiled: dict | None = None, scan: bool = True, causality: dict[str, str] | None = None) -> Block:
    """The :class:`Block` of Modelica ``model`` in ``text`` (``filename`` names it in messages).

    ``name`` is the block's name (default: the model's last name part, lower case);
    ``integrator`` is ``"auto"`` (``exact`` when the equations are linear, else ``radau``),
    ``exact``, ``rk4`` or ``radau``; ``roots`` are the source roots of the classes ``text``
    uses; ``compiled`` is :func:`front_end`'s result when the caller has it (then rumoca is not
    run); ``scan`` refuses the unsupported constructs found in ``text`` by their line first (off
    for a library's file, whose other classes may use anything: the flattened class is checked
    all the same); ``causality`` states a flange's causality (flange name -> ``effort_out`` or
    ``flow_out``) where the equations allow both (else the first they allow, ``effort_out``
    first).  Raises :class:`ModelicaError` (``file:line: what``)."""
    if integrator not in INTEGRATORS:
        raise ModelicaError(filename, None, f"integrator {integrator!r}; expected one of {', '.join(INTEGRATORS)}")
    if scan:
        refuse_unsupported(text, filename)
    fe = compiled if compiled is not None else front_end(text, model, filename, roots)
    tr = _Translation(text, filename, fe["dae"]["storage"], fe["flat"], fe["name"], name or model.split(".")[-1].lower())
    bad = [f"{k}: {v}" for k, v in (causality or {}).items() if v not in CAUSALITIES]
    if bad:
        raise ModelicaError(filename, None, f"causality {bad[0]!r}; expected one of {', '.join(CAUSALITIES)}")
    tr.causality = dict(causality or {})
    return tr.block(integrator, substeps)


def _rumoca_version() -> str:
    import rumoca

    return rumoca.version()


class _Translation:
    def __init__(self, text: str, filename: str, st: dict, flat: dict, model_name: str, name: str):
        self.text, self.filename, self.st, self.flat, self.name = text, filename, st, flat, name
        self.description = (flat.get("model_description") or "").strip() or f"Modelica model {model_name}"
        self.vars = [dict(v) for v in st["variables"]]  # array variables are expanded (_expand_arrays): a copy
        ex = st["expressions"]
        self.nodes, self.prov = ex["nodes"], ex["provenance"]
        self.env: dict = {}
        self.graph = _Graph(self.nodes, ex["operands"], _operand_starts(self.nodes), self.env, self._node_line,
                            filename, {k: v["name"] for k, v in enumerate(self.vars)}, st.get("functions") or [],
                            st.get("domains") or [])
        self.time = ca.SX.sym("t")  # the model's time (see _clock)
        self.mode_syms = {}
        self.event_fields: dict = {}
        self.solved = None
        self.param_values: dict[str, float] = {}
        self.param_syms: list[ca.SX] = []
        self.graph.structural = self._at_defaults
        self.always: dict[int, int] = {}
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
        e = self._attr_value(node)
        if not e.is_constant():
            self._err(v, f"{v['name']}: {what} must be a number")
        return float(ca.evalf(e))

    # the block
    def block(self, integrator: str, substeps: int) -> Block:
        self._refuse_flat()
        b = BlockBuilder(self.name, self.description, fidelity="modelica")
        self._expand_arrays()
        roles: dict[str, list[int]] = {}
        for k, v in enumerate(self.vars):
            if k not in self.elements:  # an array: its elements are the variables
                roles.setdefault(v["role"], []).append(k)
        bad = sorted(set(roles) - {"parameter", "input", "output", "state", "algebraic", "discrete_real",
                                   "discrete_value", "constant"})
        if bad:
            v = self.vars[roles[bad[0]][0]]
            self._err(v, f"{v['name']}: a {bad[0].replace('_', ' ')} variable is not supported (continuous Real only)")
        self._parameters(b, roles.get("constant", []) + roles.get("parameter", []))
        self.env[("time", 0)] = self.time  # replaced at the end: a clock state in ode/out, the block's t in events
        for c, cond in enumerate(self.st.get("conditions", [])):  # initial() read by an equation: false in the run
            if cond.get("node") == "initial":
                self.env[("condition", c)] = ca.SX(0.0)
        self._modes(roles.get("discrete_real", []) + roles.get("discrete_value", []))
        for k in roles.get("input", []):
            v = self.vars[k]
            self.env[("input", k)] = b.input(v["name"], *self._doc(v, "input"))
        self._assemble()
        states = roles.get("state", [])
        unknown: dict[tuple, ca.SX] = {}
        for k in states:
            v = self.vars[k]
            unit, text = self._doc(v, "state")
            start = v["attributes"].get("start")
            s0 = self._attr_value(start) if start is not None else ca.SX(0.0)
            if ca.depends_on(s0, ca.vertcat(*[self.env[("input", j)] for j in roles.get("input", [])])) \
                    if roles.get("input") else False:
                self._err(v, f"{v['name']}: the start value may depend on parameters only")
            self.env[("state", k)] = self.env[("pre_state", k)] = b.state(f"state.{v['name']}", s0, unit, text)
            unknown[("derivative", k)] = ca.SX.sym(f"der_{v['name']}")
        for k in roles.get("output", []) + roles.get("algebraic", []):
            unknown[("algebraic", k)] = ca.SX.sym(self.vars[k]["name"])  # outputs are algebraic coordinates too
        self.env.update(unknown)
        self._assemble()
        self._frozen_relations()
        flanges = self._connectors()
        residuals = self._residuals()
        solved, chosen = self._solve(b, residuals, unknown, flanges)
        demoted = [k for k in states if ("state", k) in solved]  # computed from the others (index reduction)
        if demoted:
            gone = {self.env[("state", k)].name() for k in demoted}
            b._states = [entry for entry in b._states if entry[1].name() not in gone]
        states = [k for k in states if k not in demoted]
        for k in states:
            b.der(self.env[("state", k)], solved[("derivative", k)])
        value = {key[1]: solved[key] if key in solved else self.env[key] for key in unknown if key[0] != "derivative"}
        for k in states:
            value[k] = self.env[("state", k)]
        top = [k for k in roles.get("output", []) if self._top_level(self.vars[k])]
        emit = [(k, lambda k=k: b.output(self.vars[k]["name"], value[k], *self._doc(self.vars[k], "output")))
                for k in top + [j for j in states if self._is_output(self.vars[j])]]
        emit += [(min(fl["potential"], fl["flow"]), lambda fl=fl, c=c: self._flange(b, fl, c, value))
                 for fl, (c, _) in zip(flanges, chosen)]
        for _, add in sorted(emit, key=lambda e: e[0]):  # in declaration order
            add()
        self._locals(b, value, set(top))
        for k, sym in self.mode_syms.items():  # the discrete variables, recordable too
            unit, text = self._doc(self.vars[k], "discrete variable")
            b.output(self.vars[k]["name"], sym, unit, text, local=not self._is_output(self.vars[k]))
        known = {key: solved[key] for key in unknown if key in solved}  # events read the solved variables
        self.solved = (ca.vertcat(*[unknown[k] for k in known]), ca.vertcat(*known.values())) if known else None
        self._initial(b, states, value)
        events = self._events(b)
        self._clock(b)
        self._thaw(b, events)
        return self._finish(b, integrator, substeps, events)

    def _frozen_relations(self) -> None:
        """Each relation (outside ``noEvent``: rumoca lists those only) on states, inputs or
        variables (not on ``time``, not a when-condition) read as a placeholder symbol, which
        :meth:`_thaw` replaces by a mode holding its truth in ``ode``/``out`` (Modelica's state
        event: the truth is frozen during integration and changes at a located crossing) and by
        the live relation elsewhere (indicators, updates, start values)."""
        self.frozen: dict[int, tuple[ca.SX, ca.SX]] = {}  # relation index -> (placeholder, live)
        st = self.st
        conditions = st.get("conditions", [])
        if getattr(self, "chains", None):
            return
        triggers = [a.get(key) for a in st.get("event_actions", []) for key in ("trigger", "guard")]
        for eq in st.get("discrete_real_equations", []):
            when = (eq.get("activation") or {}).get("when") or {}
            triggers += [when.get("trigger"), when.get("guard")]
        for o in st.get("discrete_value_owners", []):
            for br in o.get("branches", []):
                act = br.get("activation")
                when = (act.get("when") or {}) if isinstance(act, dict) else {}
                triggers += [when.get("trigger"), when.get("guard")]
        excluded: set[int] = set()
        for c in triggers:
            while isinstance(c, int) and 0 <= c < len(conditions):
                node = conditions[c].get("node") or {}
                if not isinstance(node, dict) or set(node) in ({"relation"}, {"not"}):
                    if isinstance(node, dict) and "relation" in node:
                        excluded.add(node["relation"])
                    c = node.get("not") if isinstance(node, dict) else None
                    continue
                if "discrete" in node:  # edge()/change(): a relation behind a Boolean; not frozen here
                    return
                break
        params = set(self.param_names)
        for r, rel in enumerate(st.get("relations", [])):
            node = rel["relation"]["expression"]
            (kind, body), = self.nodes[node].items()
            if r in excluded or kind != "binary" or body["operator"] not in _REL or node in self.graph.memo:
                continue
            try:
                live = self.graph._eval(node)
            except ModelicaError:  # one not read out of its context (a function's): left live
                continue
            syms = ca.symvar(live)
            if ca.depends_on(live, self.time) or all(s.name() in params for s in syms):
                continue
            self.frozen[r] = (ca.SX.sym(f"relation{r + 1}"), live)
            self.graph.memo[node] = self.frozen[r][0]

    def _relation_modes(self, relations: list, b: BlockBuilder) -> dict[int, ca.SX]:
        """A mode per frozen relation (:meth:`_frozen_relations`) that ``ode`` or ``out`` reads,
        holding its truth (0/1); one read by discrete equations only is settled at events."""
        out = {}
        continuous = ca.vertcat(*b._ders.values(), *[e for _, e in b._outputs])
        for r, (holder, _) in self.frozen.items():
            if not ca.depends_on(continuous, holder):
                continue
            key = -(len(self.condition_vars) + 1)
            sym = ca.SX.sym(f"mode.relation{r + 1}")
            self.mode_syms[key] = sym
            self.mode_starts.append(ca.SX(0.0))  # set in _events: the relation's truth at the start
            (_, body), = self.nodes[relations[r]["expression"]].items()
            what = (f"{_short(self.graph(body['lhs']), 40)} {_REL[body['operator']]} "
                    f"{_short(self.graph(body['rhs']), 40)}")
            self.condition_vars[key] = Var(sym.name(), "", f"the truth (0/1) of {what}, held between its crossings")
            out[r] = sym
        return out

    def _thaw(self, b: BlockBuilder, events: dict | None) -> None:
        """The frozen relations' placeholders replaced: by their modes in ``ode``/``out``, by the
        live relations elsewhere."""
        if not self.frozen:
            return
        holders = ca.vertcat(*[h for h, _ in self.frozen.values()])
        live = ca.vertcat(*[v for _, v in self.frozen.values()])
        if self.solved is not None:  # in states, inputs, parameters and modes (the solved variables' values)
            live = ca.substitute(live, *self.solved)
        held = ca.vertcat(*[self.relation_modes.get(r, v) for r, (_, v) in self.frozen.items()])
        for _ in range(len(self.frozen)):  # a relation inside another's operand
            live = ca.substitute(live, holders, live)
            held = ca.substitute(held, holders, live)

        def thaw(e, by=live):
            return e if e is None or isinstance(e, (int, float)) else ca.substitute(ca.SX(e), holders, by)

        b._ders = {k: thaw(e, held) for k, e in b._ders.items()}
        b._outputs = [(v, thaw(e, held)) for v, e in b._outputs]
        b._states = [(v, sym, thaw(s0)) for v, sym, s0 in b._states]
        if not events:
            return
        events["indicators"] = thaw(events["indicators"])
        events["updates"] = [thaw(g) for g in events["updates"]]
        xs, ms = [sym for _, sym, _ in b._states], list(self.mode_syms.values())
        # a start value read a relation's placeholder (a mode settled at the start): at the start state
        events["mode_start"] = [self._at_start(thaw(m), xs, ms, b) for m in events["mode_start"]]
        for smp in events.get("sample_times", []):
            smp.update = thaw(smp.update)

    def _expand_arrays(self) -> None:
        """Each array variable of more than one element as one scalar variable per element,
        appended to :attr:`vars` (named ``x[2]``, ``A[1,2]``; the attributes' values are taken
        element by element, :meth:`_attr_value`); :attr:`elements` maps an array's index to its
        elements' (row-major order), whose symbols :meth:`_assemble` gathers into the array's."""
        self.elements: dict[int, list[int]] = {}
        for k, v in enumerate(list(self.vars)):
            dims = self._dims(v)
            if math.prod(dims) == 1:
                continue
            if any(d < 0 for d in dims) or len(dims) > 2:
                self._err(v, f"{v['name']}: an array of dimensions [{', '.join(map(str, dims))}] is not supported "
                             f"(vectors and matrices of known sizes)")
            if v["role"] not in ("parameter", "constant", "input", "output", "state", "algebraic", "discrete_real",
                                 "discrete_value"):
                continue  # refused by its role
            self.elements[k] = []
            for j, sub in enumerate(product(*[range(1, d + 1) for d in dims])):
                attrs = {a: (("element", node, j, tuple(dims)) if a in ("start", "binding", "min", "max")
                             and isinstance(node, int) else node) for a, node in v["attributes"].items()}
                self.elements[k].append(len(self.vars))
                self.vars.append({**v, "name": f"{v['name']}[{','.join(map(str, sub))}]", "attributes": attrs,
                                  "element_of": (k, j)})

    def _attr_value(self, node) -> ca.SX:
        """The value of an attribute (``start``, ``binding``, ``min``, ``max``): its node's, or,
        for an array's element, that element of it (a scalar applies to every element)."""
        if not isinstance(node, tuple):
            return self.graph(node)
        _, n, j, dims = node
        value = self.graph(n)
        if value.numel() == 1:
            return value
        if value.numel() != math.prod(dims):
            raise ModelicaError(self.filename, self._node_line(n), f"an array value of {value.numel()} elements "
                                                                   f"for {math.prod(dims)}")
        return value[j] if len(dims) == 1 else value[divmod(j, dims[1])]

    def _assemble(self) -> None:
        """The symbols of each array variable, gathered from its elements' (a column for a
        vector, a matrix otherwise), for every coordinate kind its elements have."""
        for k, elems in self.elements.items():
            dims = self._dims(self.vars[k])
            if not elems:  # an empty array (MSL filters of order 0): an empty column or matrix of every kind
                role = self.vars[k]["role"]
                for kind in (role, f"pre_{role}", "derivative", "parameter", "algebraic"):
                    self.env.setdefault((kind, k), ca.SX(*(dims + [1])[:2]) if len(dims) == 1 else ca.SX(*dims))
                continue
            kinds = {key[0] for e in elems[:1] for key in self.env if len(key) == 2 and key[1] == e}
            for kind in kinds:
                if (kind, k) in self.env or not all((kind, e) in self.env for e in elems):
                    continue
                col = ca.vertcat(*[self.env[(kind, e)] for e in elems])
                self.env[(kind, k)] = col if len(dims) == 1 else ca.reshape(col, dims[1], dims[0]).T

    def _dims(self, v: dict) -> list[int]:
        if "element_of" in v:
            return []
        types = self.st.get("value_types") or []
        k = v.get("value_type")
        dims = types[k].get("dimensions", []) if isinstance(k, int) and k < len(types) else []
        return [d if isinstance(d, int) else -1 for d in dims]

    def _top_level(self, v: dict) -> bool:
        """An output of the class itself (not of one of its components, ``sine1.y``)."""
        return "." not in v["name"] and "[" not in v["name"]

    def _locals(self, b: BlockBuilder, value: dict, done: set[int]) -> None:
        """Every other variable of the model (states, algebraic variables, the outputs of its
        components) as an FMI local under its Modelica name, so a scene can record it."""
        taken = {v.name for v, _ in b._outputs} | {v.name for v, _ in b._inputs}
        for k, v in enumerate(self.vars):
            if k in done or k not in value or v["name"] in taken or v["role"] not in ("state", "algebraic", "output"):
                continue
            unit, text = self._doc(v, "variable")
            b.output(v["name"], value[k], unit, text, local=True)
            taken.add(v["name"])

    def _finish(self, b: BlockBuilder, integrator: str, substeps: int, events: dict | None = None) -> Block:
        if integrator != "auto":
            return b.build(integrator=integrator, substeps=substeps, units_required=False, events=events)
        from .integrators import affine_parts

        probe = b.build(integrator="rk4", substeps=substeps, units_required=False, events=events)  # (building does not change the builder)
        if not probe.states or affine_parts(probe) is not None:
            exact = dataclasses.replace(probe, integrator="exact" if probe.states else "none")
            exact.check()
            return exact
        return b.build(integrator="radau", substeps=substeps, units_required=False, events=events)

    # events (docs/explanation/events.md): when-equations, reinit, pre, relations as indicators
    def _modes(self, keys: list[int]) -> None:
        """The discrete Real variables as the block's modes (``pre(v)`` is the mode's left value)."""
        self.mode_syms: dict[int, ca.SX] = {}
        self.mode_starts: list[ca.SX] = []
        for k in keys:
            v = self.vars[k]
            sym = ca.SX.sym(f"mode.{v['name']}")
            kind = v["role"]  # discrete_real, or discrete_value (a Boolean or Integer held as a real)
            self.env[(kind, k)] = self.env[(f"pre_{kind}", k)] = sym
            start = v["attributes"].get("start")
            self.mode_starts.append(self._attr_value(start) if start is not None else ca.SX(0.0))
            self.mode_syms[k] = sym
        keys = list(self.mode_syms)
        for item in self.st.get("initial_discrete_values", []):  # an initial algorithm's assignments, in order
            if item["target"] not in self.mode_syms:
                self._fail_span(item, f"initial algorithm: {self.vars[item['target']]['name']} is not a discrete "
                                      f"variable (an initial algorithm may set those only)")
            value = self.graph(item["value"])  # of parameters (states have no value yet: refused by the graph)
            value = ca.substitute(value, ca.vertcat(*self.mode_syms.values()), ca.vertcat(*self.mode_starts))
            self.mode_starts[keys.index(item["target"])] = value

    def _clock(self, b: BlockBuilder) -> None:
        """``time`` in the continuous equations becomes a clock state (d/dt = 1 from 0 at the
        run's start: blocks are autonomous); none is added when they do not use it."""
        uses = any(ca.depends_on(e, self.time) for e in list(b._ders.values()) + [e for _, e in b._outputs]) or \
            any(ca.depends_on(ca.SX(s0), self.time) for _, _, s0 in b._states)
        if not uses:
            return
        clock = b.state("state.time", 0.0, "s", "the model's time: a clock state, d/dt = 1 from 0 at the run's start")
        b.der(clock, 1.0)
        b._ders = {k: ca.substitute(e, self.time, clock) for k, e in b._ders.items()}
        b._outputs = [(v, ca.substitute(e, self.time, clock)) for v, e in b._outputs]
        if self.event_fields:  # the clock is a state the updates keep: its row goes after the others
            nx = len(b._states) - 1
            self.event_fields["updates"] = [None if g is None else ca.vertcat(g[:nx], clock, g[nx:])
                                            for g in self.event_fields["updates"]]
            for smp in self.event_fields.get("sample_times", []):
                if smp.update is not None:
                    smp.update = ca.vertcat(smp.update[:nx], clock, smp.update[nx:])

    def _events(self, b: BlockBuilder) -> dict | None:
        """The block's event fields from rumoca's roots, conditions, event actions and discrete
        equations: each relation a root watches is an indicator ``lhs - rhs`` (a ``<``/``<=``
        fires falling, ``>``/``>=`` rising, for a when-clause; either way when only an
        if-expression reads it); a when-clause's update applies its ``reinit``s to the states and
        solves its discrete equations for the modes' new values (``pre(v)`` the left values)."""
        st = self.st
        self.event_fields: dict = {}
        for key, what in (("delays", "delay()"), ("previous_values", "previous()")):
            if st.get(key):
                item = st[key][0]
                self._fail_span(item if isinstance(item, dict) else {}, f"{what} is not supported yet")
        roots = [r["root"] for r in st.get("roots", [])]
        always = self._always()
        self.assertions: list[tuple] = []
        actions = [a for a in st.get("event_actions", []) if not self._assert(a)]
        if not roots and not self.mode_syms and not st.get("time_events") and not st.get("clocks") and \
                not self.chains and not self.assertions:
            return None
        relations = [r["relation"] for r in st.get("relations", [])]
        conditions = st.get("conditions", [])
        # each relation's truth at an event, read on its far side (the discrete equations settled there)
        self.far_sides = {}
        for rel in relations:
            try:
                self.far_sides[rel["expression"]] = self._far_side(rel, b)
            except ModelicaError:  # one not read out of its context (a function's): the settling reads none
                continue
        chains = self._chain_modes(conditions, relations, b)
        self._assertion_modes(b)
        self.relation_modes = self._relation_modes(relations, b)
        xs = [sym for _, sym, _ in b._states]
        ms = list(self.mode_syms.values())
        indicators, directions, names, updates = [], [], [], []
        by_relation: dict[int, int] = {}

        def indicator(r: int) -> None:  # relation r as an indicator lhs - rhs (falling for <, <=)
            rel = relations[r]
            (kind, body), = self.nodes[rel["expression"]].items()
            if kind != "binary" or body["operator"] not in ("less", "less_equal", "greater", "greater_equal"):
                self._fail_node(rel["expression"], "a relation other than <, <=, >, >= as an event")
            z = self.graph(body["lhs"]) - self.graph(body["rhs"])
            by_relation[r] = len(indicators)
            indicators.append(z)
            directions.append(FALLING if body["operator"] in ("less", "less_equal") else RISING)
            names.append(f"{_short(self.graph(body['lhs']), 40)} {_REL[body['operator']]} "
                         f"{_short(self.graph(body['rhs']), 40)}")
            updates.append(None)

        for root in roots:
            indicator(root["relation"])
        for cond, level, message, line, zero in self.assertions:  # a warning's relation: located like the others
            if zero is not None:
                indicators.append(zero)
                directions.append(EITHER)
                names.append(f"assert at line {line}")
                updates.append(None)
        triggers: dict[int, list] = {}
        for act in actions:
            triggers.setdefault(act["trigger"], []).append(("action", act))
        for eq in st.get("discrete_real_equations", []):
            when = (eq.get("activation") or {}).get("when")
            if when is None:
                self._fail_span(eq, "a discrete equation outside a when-clause")
            triggers.setdefault(when["trigger"], []).append(("equation", eq))
        for trig, k, val in self.when_values:  # a Boolean or Integer assigned in a when-clause: v = value
            triggers.setdefault(trig, []).append(("value", {**val, "target": k}))
        fired = set()
        periodic = []  # (period, start, update, name) of the when-clauses on sample() and initial()
        in_chain = {c for chain in chains for c, _, _ in chain}
        for trig, items in triggers.items():
            if trig in in_chain:
                continue
            node = (conditions[trig].get("node") or {}) if trig < len(conditions) else {}
            if node == "initial":  # when initial(): a time event at the run's start, t = 0
                periodic.append((ONCE, 0.0, self._update(items, xs, ms, b), "when initial()"))
                continue
            if set(node) == {"clock"}:
                periodic.append(self._sample(node["clock"], items, xs, ms, b))
                continue
            either = False
            if set(node) == {"discrete"}:  # edge(b) or change(b) of a Boolean b = relation: that relation's crossing
                node = self._edge(node["discrete"], relations)
                either = node.pop("either", False)
            if set(node) == {"relation"} and node["relation"] not in by_relation and 0 <= node["relation"] < len(relations):
                # a relation rumoca made a time event (when time > 0.5): located as an indicator in time,
                # so a parameter in it stays settable
                indicator(node["relation"])
            if set(node) != {"relation"} or node["relation"] not in by_relation or by_relation[node["relation"]] in fired:
                where = conditions[trig] if trig < len(conditions) and conditions[trig].get("provenance") else items[0][1]
                self._fail_span(where, "a when-condition other than one relation, initial(), one sample() or "
                                             "one edge()/change() of a Boolean given by a relation (and/or of "
                                             "conditions, two when-clauses on one relation)")
            i = by_relation[node["relation"]]
            updates[i] = self._update(items, xs, ms, b)
            directions[i] = EITHER if either else directions[i]
            fired.add(i)
        for chain in chains:  # when/elsewhen: the first branch whose condition becomes true wins
            for c, _, _ in chain:
                i = by_relation.get((conditions[c].get("node") or {}).get("relation"))
                if i is None or i in fired:
                    self._fail_span(conditions[c], "an elsewhen branch's condition other than one relation on "
                                                   "states, inputs or parameters (or a relation another "
                                                   "when-clause uses too)")
                fired.add(i)
            g = self._chain_update(chain, triggers, xs, ms, b)
            for c, _, _ in chain:
                i = by_relation[conditions[c]["node"]["relation"]]
                updates[i], directions[i] = g, EITHER  # either way: the condition's truth is a mode
        for i in range(len(indicators)):
            if i not in fired:
                directions[i] = EITHER  # a relation read by an if-expression: the step restarts where it switches
        keys = list(self.mode_syms)
        for r, sym in self.relation_modes.items():  # its mode takes the relation's truth at its crossing
            j = [k for k, m in enumerate(ms) if m is sym][0]
            self.mode_starts[keys.index([k for k in keys if self.mode_syms[k] is sym][0])] = \
                self._at_start(self.frozen[r][1], xs, ms, b)
            if r not in by_relation:
                indicator(r)
            i = by_relation[r]
            if i in fired:
                continue
            directions[i] = EITHER
            rows = [*xs, *ms]
            rows[len(xs) + j] = self._far_side(relations[r], b)
            updates[i] = ca.vertcat(*rows)
        if self.solved is not None:  # indicators and updates in states, inputs, parameters and modes only
            indicators = [ca.substitute(z, *self.solved) for z in indicators]
            updates = [None if g is None else ca.substitute(g, *self.solved) for g in updates]
            periodic = [(T, t0, ca.substitute(g, *self.solved), name) for T, t0, g, name in periodic]
        samples = []
        if always:  # the modes' start values settled at the start state, t = 0 (inputs 0 until the initial event)
            m0 = self._settle(xs, ms)
            if xs:
                m0 = ca.substitute(m0, ca.vertcat(*xs), ca.vertcat(*[ca.SX(s0) for _, _, s0 in b._states]))
            us = [sym for _, sym in b._inputs]
            m0 = ca.substitute(m0, ca.vertcat(self.time, *us), ca.SX.zeros(1 + len(us)))
            m0 = ca.substitute(m0, ca.vertcat(*ms), ca.vertcat(*self.mode_starts))
            self.mode_starts = [m0[j] for j in range(m0.numel())]
        if chains:  # a condition's mode starts at its truth at the start (a when fires where it becomes true)
            self._chain_starts(chains, xs, ms, b)
        if always:  # every event ends by settling the always-active discrete equations
            updates = [self._settled(xs, ms, g) for g in updates]
            samples.append(Sample(ONCE, 0.0, self._settled(xs, ms, None), "initial"))
        for te in st.get("time_events", []):  # an instant known in advance (a relation on time)
            inst = te.get("instant") if isinstance(te, dict) else None
            if not isinstance(inst, dict) or not inst.get("den"):
                self._fail_span(te if isinstance(te, dict) else {}, "a time event other than a fixed instant")
            samples.append(Sample(ONCE, inst["num"] / inst["den"], self._settled(xs, ms, None) if always else None,
                                  f"time event at {inst['num'] / inst['den']:g} s"))
        for T, t0, g, name in periodic:  # sample(start, interval): start + k interval, k = 0, 1, ...; initial()
            samples.append(Sample(T, t0, self._settled(xs, ms, g) if always else g, name))
        if not indicators and not samples:  # modes without events (set by an initial algorithm): one identity event
            samples.append(Sample(ONCE, 0.0, None, "initial"))
        if self.assert_modes:  # every event ends by latching the assertions; they start at their start value
            updates = [self._latched(xs, ms, g) for g in updates]
            for smp in samples:
                smp.update = self._latched(xs, ms, smp.update)
            keys = list(self.mode_syms)
            for sym, cond in self.assert_modes:
                j = [k for k, m in enumerate(ms) if m is sym][0]
                self.mode_starts[j] = 1 - self._at_start(cond, xs, ms, b)
        self.event_fields = {
            "modes": [self.condition_vars[k] if k < 0 else
                      Var(f"mode.{self.vars[k]['name']}", *self._doc(self.vars[k], "discrete variable"))
                      for k in self.mode_syms],
            "m": ca.vertcat(*ms) if ms else ca.SX(0, 1), "mode_start": self.mode_starts, "t": self.time,
            "indicators": ca.vertcat(*indicators) if indicators else ca.SX(0, 1), "directions": directions,
            "event_names": names, "updates": updates, "sample_times": samples}
        return self.event_fields

    def _chain_modes(self, conditions: list, relations: list, b: BlockBuilder) -> list[list[tuple]]:
        """The when/elsewhen chains as ``[(condition, truth, mode)]`` per branch: each branch's
        condition (rumoca's, found by its source span), its truth (0/1 in ``t, x, u, p, m`` and the
        solved variables) and a mode holding that truth's left value (``pre`` of the condition),
        added to :attr:`mode_syms` under a negative key."""
        self.condition_vars: dict[int, Var] = {}
        by_span = {}
        for c, cond in enumerate(conditions):
            span = (cond.get("provenance") or {}).get("span") or {}
            by_span.setdefault((span.get("source"), span.get("start")), c)
        out = []
        for j, spans in enumerate(self.chains):
            chain = []
            for k, span in enumerate(spans):
                c = by_span.get(span)
                node = (conditions[c].get("node") or {}) if c is not None else {}
                if c is None or set(node) != {"relation"}:
                    raise ModelicaError(self.filename, self._offset_line(span[1]),
                                        "an elsewhen branch's condition other than one relation on states, "
                                        "inputs or parameters (initial(), sample(), edge() or and/or in a chain)")
                truth = self._far_side(relations[node["relation"]], b)
                key = -(len(self.condition_vars) + 1)
                name = f"mode.when{j + 1}.c{k + 1}"
                sym = ca.SX.sym(name)
                self.mode_syms[key] = sym
                self.mode_starts.append(ca.SX(0.0))  # set by _chain_starts
                line = self._offset_line(span[1])
                self.condition_vars[key] = Var(name, "", f"the truth (0/1) of branch {k + 1}'s condition of the "
                                                         f"when/elsewhen at line {line}: {_short(truth, 60)}")
                chain.append((c, truth, sym))
            out.append(chain)
        return out

    def _far_side(self, relation: dict, b: BlockBuilder) -> ca.SX:
        """A relation's truth (0/1) at an event, read on the side it moves to: where its indicator
        ``z = lhs - rhs`` is exactly zero (the event located on the threshold, e.g. ``x > 1`` on
        ``x = t`` at a grid instant ``t = 1``) the sign of ``dz/dt`` along the states' derivatives
        decides (inputs' slopes are not seen), so the branch crossing there applies there and not at
        the next event; where ``dz/dt`` is zero too, the relation as written.  Stateless, so two
        conditions crossing at one instant read the same truth in each update."""
        (kind, body), = self.nodes[relation["expression"]].items()
        written = self.graph(relation["expression"])
        if kind != "binary" or body["operator"] not in _REL:
            return written
        z = self.graph(body["lhs"]) - self.graph(body["rhs"])
        if self.solved is not None:
            z = ca.substitute(z, *self.solved)
        xs = [sym for _, sym, _ in b._states]
        rates = [b._ders.get(sym.name(), ca.SX(0.0)) for sym in xs]
        zdot = ca.jtimes(z, ca.vertcat(self.time, *xs), ca.vertcat(1.0, *rates))
        moving = zdot > 0 if body["operator"] in ("greater", "greater_equal") else zdot < 0
        return ca.if_else(ca.logic_and(z == 0, zdot != 0), moving, written)

    def _chain_update(self, chain: list, triggers: dict, xs: list, ms: list, b: BlockBuilder) -> ca.SX:
        """``[x+; m+]`` of a when/elsewhen chain at any of its conditions' crossings: the first
        branch whose condition becomes true (true now, false before: its mode) applies its
        equations and reinits, the others nothing; every condition's mode takes its truth now."""
        ident = ca.vertcat(*xs, *ms)
        g = ident
        for c, truth, sym in reversed(chain):
            items = triggers.get(c, [])
            branch = self._update(items, xs, ms, b) if items else ident
            g = ca.if_else(ca.logic_and(truth, ca.logic_not(sym)), branch, g)
        rows = [g[r] for r in range(g.numel())]
        for _, truth, sym in chain:
            rows[len(xs) + [j for j, m in enumerate(ms) if m is sym or ca.is_equal(m, sym)][0]] = truth
        return ca.vertcat(*rows)

    def _chain_starts(self, chains: list, xs: list, ms: list, b: BlockBuilder) -> None:
        """Each condition mode's start: its condition's truth at the start state, ``t = 0``
        (inputs 0), so a condition true from the start does not fire (as a when-clause's)."""
        keys = list(self.mode_syms)
        for chain in chains:
            for _, truth, sym in chain:
                self.mode_starts[keys.index([k for k in keys if self.mode_syms[k] is sym][0])] = \
                    self._at_start(truth, xs, ms, b)

    def _at_start(self, e: ca.SX, xs: list, ms: list, b: BlockBuilder) -> ca.SX:
        """``e`` at the start: the states' and modes' start values, ``t = 0``, inputs 0 (an
        expression of the parameters)."""
        v = ca.substitute(e, *self.solved) if self.solved is not None else e
        if xs:
            v = ca.substitute(v, ca.vertcat(*xs), ca.vertcat(*[ca.SX(s0) for _, _, s0 in b._states]))
        us = [u for _, u in b._inputs]
        v = ca.substitute(v, ca.vertcat(self.time, *us), ca.SX.zeros(1 + len(us)))
        return ca.substitute(v, ca.vertcat(*ms), ca.vertcat(*self.mode_starts)) if ms else v

    def _at_defaults(self, e: ca.SX) -> ca.SX:
        """``e`` at the parameters' default values (for an array's size, which rumoca fixed)."""
        if not self.param_syms:
            return e
        return ca.substitute(e, ca.vertcat(*self.param_syms),
                             ca.vertcat(*[ca.SX(self.param_values[p.name()]) for p in self.param_syms]))

    @property
    def param_names(self) -> set[str]:
        return set(self.param_values)

    def _initial(self, b: BlockBuilder, states: list[int], value: dict) -> None:
        """The start values the initial equations determine (``initial equation`` sections and
        ``fixed = true`` on any variable): the states without a fixed start are the unknowns
        (those the equations reach, chosen to keep the system structurally regular; the others
        keep their start values), solved symbolically in the parameters (a linear system by a
        sparse solve, a nonlinear one by Newton from the start values)."""
        ops = self.st.get("initialization_equation_operations", [])
        rows, lines = [], []
        for op in ops:
            (kind, body), = op.items()
            if kind != "residual":
                self._fail_span(body, f"an initial equation of kind {kind!r} is not supported")
            rows.append(self.graph(body["residual"]))
            lines.append(body)
        for k, v in enumerate(self.vars):
            if v["role"] in ("algebraic", "output") and self._fixed(k) and v["attributes"].get("start") is not None \
                    and k in value:
                rows.append(value[k] - self._attr_value(v["attributes"]["start"]))
        if not rows:
            return
        xs = {self.env[("state", k)].name(): k for k in states}
        starts = {sym.name(): s0 for _, sym, s0 in b._states}
        syms = [sym for _, sym, _ in b._states]
        E = ca.vertcat(*rows)
        if self.solved is not None:
            E = ca.substitute(E, *self.solved)
        E = ca.substitute(E, self.time, ca.SX(0.0))
        if self.mode_syms:
            E = ca.substitute(E, ca.vertcat(*self.mode_syms.values()), ca.vertcat(*self.mode_starts))
        us = [sym for _, sym in b._inputs]
        if us and ca.depends_on(E, ca.vertcat(*us)):
            self._fail_span(lines[0] if lines else {}, "an initial equation reads an input (start values may "
                                                       "depend on parameters only)")
        free = [s for s in syms if s.name() in xs and not self._fixed(xs[s.name()])]
        chosen: list = []
        for s in free:  # the unknowns: a largest structurally regular choice, in declaration order
            if len(chosen) == E.numel():
                break
            trial = chosen + [s]
            if ca.sprank(ca.jacobian_sparsity(E, ca.vertcat(*trial))) == len(trial):
                chosen = trial
        if len(chosen) != E.numel():
            self._fail_span(lines[0] if lines else {}, f"the initial equations ({E.numel()}, with the fixed start "
                                                       f"values of variables) do not determine as many states "
                                                       f"(found {len(chosen)} they can fix)")
        others = [s for s in syms if not any(s is c or ca.is_equal(s, c) for c in chosen)]
        if others:
            E = ca.substitute(E, ca.vertcat(*others), ca.vertcat(*[ca.SX(starts[s.name()]) for s in others]))
        Z = ca.vertcat(*chosen)
        J = ca.jacobian(E, Z)
        if not ca.depends_on(J, Z):
            sol = ca.solve(J, -ca.substitute(E, Z, ca.SX.zeros(Z.shape)))
        else:
            sol = ca.vertcat(*[ca.SX(starts[s.name()]) for s in chosen])
            for _ in range(NEWTON_ITERATIONS):
                sol = sol - ca.solve(ca.substitute(J, Z, sol), ca.substitute(E, Z, sol))
        new = {c.name(): sol[j] for j, c in enumerate(chosen)}
        b._states = [(var, sym, new.get(sym.name(), s0)) for var, sym, s0 in b._states]

    def _always(self) -> dict[int, int]:
        """The always-active discrete equations of Boolean and Integer variables (``b = x > 1``):
        variable index -> the node of its value.  A when-assigned one is refused by its line."""
        out = {}
        self.when_values: list[tuple[int, int, dict]] = []  # (trigger, variable, owner) of when-assigned ones
        for o in self.st.get("discrete_value_owners", []):
            br = o.get("branches", [])
            whens = [(b.get("activation") or {}).get("when") if isinstance(b.get("activation"), dict) else None
                     for b in br]
            if len(o["targets"]) == 1 and len(br) > 1 and all(w is not None and w.get("trigger") == w.get("guard")
                                                              and len(b.get("values", [])) == 1
                                                              for w, b in zip(whens, br)):
                # assigned in the branches of a when/elsewhen chain (or of several when-clauses)
                self.when_values += [(w["trigger"], o["targets"][0], b["values"][0]) for w, b in zip(whens, br)]
                continue
            if len(o["targets"]) != 1 or len(br) != 1 or len(br[0].get("values", [])) != 1:
                self._fail_span(o, f"{self.vars[o['targets'][0]]['name']}: a Boolean or Integer variable assigned in "
                                   f"more than one branch (an if-equation) is not supported yet")
            act = br[0].get("activation")
            when = act.get("when") if isinstance(act, dict) else None
            if when is not None and when.get("trigger") == when.get("guard"):
                self.when_values.append((when["trigger"], o["targets"][0], br[0]["values"][0]))
                continue
            if act != "always":
                self._fail_span(o, f"{self.vars[o['targets'][0]]['name']}: a Boolean or Integer variable assigned "
                                   f"under a condition other than a when-clause's is not supported yet")
            out[o["targets"][0]] = br[0]["values"][0]["value"]
        self.always = out
        return out

    def _settle(self, xs: list, ms: list) -> ca.SX:
        """The modes after solving the always-active discrete equations at ``(t, x, u, p, m)``
        (a fixed point, reached in at most one round per such variable: they are acyclic), each
        relation read on its far side (:meth:`_far_side`)."""
        keys = list(self.mode_syms)
        g = dataclasses.replace(self.graph)
        g.memo.update(self.far_sides)  # a relation on its threshold at the event: the side it moves to
        values = {k: g(node) for k, node in self.always.items()}
        if self.solved is not None:
            values = {k: ca.substitute(v, *self.solved) for k, v in values.items()}
        m = ca.vertcat(*ms)
        f = ca.vertcat(*[values.get(k, self.mode_syms[k]) for k in keys])
        cur = m
        for _ in range(len(values) + 1):
            cur = ca.substitute(f, m, cur)
        return cur

    def _settled(self, xs: list, ms: list, g: ca.SX | None) -> ca.SX:
        """The update ``g`` (None: the identity) followed by the settling of the discrete equations."""
        nx = len(xs)
        x_new = ca.vertcat(*xs) if g is None else g[:nx]
        m_new = ca.vertcat(*ms) if g is None else g[nx:]
        settled = self._settle(xs, ms)
        if xs:
            settled = ca.substitute(settled, ca.vertcat(*xs), x_new)
        settled = ca.substitute(settled, ca.vertcat(*ms), m_new)
        return ca.vertcat(x_new, settled)

    def _edge(self, i: int, relations: list) -> dict:
        """``{"relation": r}`` when node ``i`` is ``edge(b)`` (rumoca: ``b and not pre(b)``) or
        ``change(b)`` (``b <> pre(b)``, then also ``"either": True``) of a Boolean ``b`` whose
        always-active equation is relation ``r``; ``{}`` otherwise."""
        def ref(j: int, kind: str):
            c = self.nodes[j].get("coordinate")
            return c.get(kind) if isinstance(c, dict) else None

        (kind, body), = self.nodes[i].items()
        if kind != "binary" or body["operator"] not in ("and", "not_equal"):
            return {}
        k = ref(body["lhs"], "discrete_value")
        if body["operator"] == "and":
            rhs = self.nodes[body["rhs"]].get("unary") or {}
            pre = ref(rhs["operand"], "pre_discrete_value") if rhs.get("operator") == "not" else None
        else:
            pre = ref(body["rhs"], "pre_discrete_value")
        if k is None or pre != k or k not in self.always:
            return {}
        found = [r for r, rel in enumerate(relations) if rel["expression"] == self.always[k]]
        return {"relation": found[0], "either": body["operator"] == "not_equal"} if found else {}

    def _sample(self, c: int, items: list, xs: list, ms: list, b: BlockBuilder) -> tuple:
        """``(interval [s], start [s], update, name)`` of a when-clause on ``sample(start,
        interval)`` (rumoca's periodic clock ``c``): a time event at ``start + k interval``."""
        clock = self.st["clocks"][c]
        lattice = (clock.get("kind") or {}).get("periodic", {}).get("lattice") if isinstance(clock, dict) else None
        if not lattice or not lattice.get("period", {}).get("den") or not lattice.get("phase", {}).get("den"):
            self._fail_span(clock if isinstance(clock, dict) else {}, "a clock other than sample(start, interval) "
                                                                      "with constant arguments")
        period = lattice["period"]["num"] / lattice["period"]["den"]
        start = lattice["phase"]["num"] / lattice["phase"]["den"]
        if not period > 0:
            self._fail_span(clock, f"sample(): the interval must be positive (got {period:g} s)")
        return period, start, self._update(items, xs, ms, b), f"sample({start:g}, {period:g})"

    def _assert(self, act: dict) -> bool:
        """Whether the event action is an assertion (``assert(c, msg)``, at level error or
        warning).  One on parameters only is checked here, at the parameters' defaults (a failing
        one refused with its line); one on variables is kept in :attr:`assertions` as
        ``(condition, level, message, line)``, checked during the run (:meth:`_assertion_modes`)."""
        kind = act.get("kind") or {}
        if "assert" not in kind and "warning" not in kind:
            return False
        conditions = self.st["conditions"]
        zero = None  # a warning's relation as an indicator (rumoca wraps its condition in noEvent)
        if "warning" in kind:
            level, node = "warning", kind["warning"].get("condition")
            cond = self.graph(node) if node is not None else None
            inner = self.nodes[node] if node is not None else {}
            if (inner.get("builtin") or {}).get("builtin") == "no_event":
                rel = self.nodes[self.graph.operands[self.graph.starts[node]]].get("binary") or {}
                if rel.get("operator") in _REL:
                    zero = self.graph(rel["lhs"]) - self.graph(rel["rhs"])
        else:
            level = "error"
            guard = (conditions[act["guard"]].get("node") or {}) if act.get("guard") is not None else {}
            inner = (conditions[guard["not"]].get("node") or {}) if isinstance(guard, dict) and "not" in guard else {}
            cond = None
            if "discrete" in inner:
                cond = self.graph(inner["discrete"])
            elif "relation" in inner:
                cond = self.graph(self.st["relations"][inner["relation"]]["relation"]["expression"])
        if cond is None:
            self._fail_span(act, "an assert whose condition is not understood here")
        if self.solved is not None:
            cond = ca.substitute(cond, *self.solved)
        params = [sym for sym in ca.symvar(cond) if sym.name() in self.param_names]
        line = self._offset_line(((act.get("provenance") or {}).get("span") or {}).get("start"))
        msg_node = kind[level if level == "warning" else "assert"].get("message")
        lit = (self.nodes[msg_node].get("literal") or {}) if isinstance(msg_node, int) else {}
        message = lit.get("string") if isinstance(lit, dict) and "string" in lit else "(its message is not a literal)"
        if len(params) == len(ca.symvar(cond)):
            value = ca.Function("a", [ca.vertcat(*params) if params else ca.SX(0, 1)], [cond])(
                [self.param_values[s.name()] for s in params])
            if float(value) == 0.0 and level == "error":
                self._fail_span(act, f"an assert on the parameters fails at their values: {message}")
            return True
        self.assertions.append((cond, level, message, line, zero))
        return True

    def _assertion_modes(self, b: BlockBuilder) -> None:
        """Each assertion on variables as a latched mode ``assert.<line>`` (0 while its
        condition has held, 1 once it failed at an event or the start: its relations are
        indicators, so a crossing is located inside the step), recorded as a local output.  At
        level error it is rated [-0.5, 0.5] with the assertion's message as the rating's source,
        so the run-time guard (``guards.rated``) ends the run ``out_of_limits`` quoting it; at
        level warning it is only recorded."""
        self.assert_modes: list[tuple[ca.SX, ca.SX]] = []  # (mode, condition)
        taken: set[str] = set()
        for cond, level, message, line, _ in self.assertions:
            name = f"assert.line{line}" if f"assert.line{line}" not in taken else f"assert.line{line}_{len(taken)}"
            taken.add(name)
            sym = ca.SX.sym(f"mode.{name}")
            key = -(len(self.condition_vars) + 1)
            self.mode_syms[key] = sym
            self.mode_starts.append(ca.SX(0.0))  # set in _events: 1 - the condition at the start
            where = f"{self.filename}:{line}" if line else self.filename
            text = f"assert at {where}: \"{message}\" (level {level})"
            self.condition_vars[key] = Var(f"mode.{name}", "", f"1 once the {text} failed, else 0")
            b.output(name, sym, "", f"1 once the {text} failed, else 0 (latched)", local=True)
            if level == "error":
                b.rating(name, -0.5, 0.5, "rated", text)
            self.assert_modes.append((sym, cond))

    def _latched(self, xs: list, ms: list, g: ca.SX | None) -> ca.SX:
        """The update ``g`` (None: the identity) followed by the assertions' latches, each
        ``max(m, 1 - condition)`` at the updated state."""
        nx = len(xs)
        g = ca.vertcat(*xs, *ms) if g is None else g
        rows = [g[r] for r in range(g.numel())]
        for sym, cond in self.assert_modes:
            c = ca.substitute(cond, ca.vertcat(*xs, *ms), g) if xs or ms else cond
            j = nx + [k for k, m in enumerate(ms) if m is sym][0]
            rows[j] = ca.fmax(rows[j], 1 - c)
        return ca.vertcat(*rows)

    def _update(self, items: list, xs: list, ms: list, b: BlockBuilder) -> ca.SX:
        """``[x+; m+]`` of one when-clause: its discrete equations solved for the modes' new
        values, then its reinits (which may read them)."""
        new = {k: ca.SX.sym(f"new.{self.vars[k]['name'] if k >= 0 else self.mode_syms[k].name()}")
               for k in self.mode_syms}
        env = dict(self.env)
        env.update({(self.vars[k]["role"], k): s for k, s in new.items() if k >= 0})
        g = dataclasses.replace(self.graph, env=env)
        eqs = [g(it["residual"]) if kind == "equation" else new[it["target"]] - g(it["value"])
               for kind, it in items if kind in ("equation", "value")]
        for kind, it in items:
            if kind == "action" and it.get("guard") != it.get("trigger"):
                self._fail_span(it, "elsewhen is not supported yet (one when-clause per condition)")
        solved: dict = {}
        if eqs:
            unknowns = [s for s in new.values() if any(ca.depends_on(e, s) for e in eqs)]
            R, Z = ca.vertcat(*eqs), ca.vertcat(*unknowns)
            J = ca.jacobian(R, Z)
            if len(unknowns) != len(eqs) or ca.depends_on(J, Z):
                self._fail_span(items[0][1], "the equations of this when-clause do not determine its discrete "
                                             "variables one by one (each must be assigned once, linearly)")
            sol = ca.solve(J, -ca.substitute(R, Z, ca.SX.zeros(Z.shape)))
            solved = {unknowns[j].name(): sol[j] for j in range(len(unknowns))}
        m_new = []
        for k, m in zip(self.mode_syms, ms):
            m_new.append(solved.get(new[k].name(), m))
        subst_from = ca.vertcat(*new.values()) if new else ca.SX(0, 1)
        subst_to = ca.vertcat(*m_new) if m_new else ca.SX(0, 1)
        x_new = list(xs)
        for kind, it in items:
            if kind != "action":
                continue
            (akind, body), = it["kind"].items()
            if akind != "reinitialize":
                self._fail_span(it, f"the event action {akind!r} is not supported")
            target = self.env.get(("state", body["state"]))
            if target is None or not any(ca.is_equal(target, x) for x in xs):
                self._fail_span(it, f"reinit of {self.vars[body['state']]['name']}, which is not a state here")
            value = g(body["value"])
            value = ca.substitute(value, subst_from, subst_to) if new else value
            x_new[[j for j, x in enumerate(xs) if ca.is_equal(x, target)][0]] = value
        return ca.vertcat(*(x_new + m_new))

    def _fail_span(self, item: dict, what: str):
        span = (item.get("provenance") or {}).get("span") or {}
        raise ModelicaError(self.filename, self._offset_line(span.get("start")), what)

    def _fail_node(self, i: int, what: str):
        raise ModelicaError(self.filename, self._node_line(i), what)

    @staticmethod
    def _is_output(v: dict) -> bool:
        return v["attributes"].get("causality") == "output"

    def _doc(self, v: dict, kind: str) -> tuple[str, str]:
        """``(unit, description)`` of a variable as the block declares it.  Both are optional in
        Modelica: a missing unit is exported as none (unknown, a wildcard in the unit check), a
        unit :mod:`models.units` does not read is shown in the description and exported as none,
        and the description then says so."""
        a = v["attributes"]
        unit, text = (a.get("unit") or "").strip(), (a.get("description") or "").strip()
        note = ""
        if not unit:
            note = "unit unknown: none declared"
        elif units.parse(unit) is None:
            note, unit = f"unit {unit!r} unknown here: not checked", ""
        if note:
            text = f"{text} ({note})" if text else f"{kind} {v['name']} (no description; {note})"
        return unit, text or f"{kind} {v['name']} (no description)"

    def _scalar(self, v: dict) -> str:
        types = self.st.get("value_types") or []
        k = v.get("value_type")
        return types[k].get("scalar", "real") if isinstance(k, int) and k < len(types) else "real"

    def _parameters(self, b: BlockBuilder, keys: list[int]) -> None:
        """The parameters and constants, each after those its value reads (in rounds: a binding
        may name one declared later)."""
        pending = list(keys)
        self._assemble()  # the empty arrays
        while pending:
            left = []
            for k in pending:
                try:
                    self._parameter(b, k)
                    if "element_of" in self.vars[k]:
                        self._assemble()
                except ModelicaError as exc:
                    if "parameter is not supported here" not in exc.message and \
                            "constant is not supported here" not in exc.message:
                        raise
                    left.append(k)
            if len(left) == len(pending):
                self._parameter(b, left[0])  # raises: a cycle, or a reference to no parameter
            pending = left

    def _parameter(self, b: BlockBuilder, k: int) -> None:
        v = self.vars[k]
        a = v["attributes"]
        node = a.get("binding") if a.get("binding") is not None else a.get("start")
        if self._scalar(v) == "string":  # a String parameter (a file or table name): not a number, not exported
            return
        if node is None:
            self._err(v, f"parameter {v['name']!r} has no value")
        value = self._attr_value(node)
        if v["name"] in self.clocked:  # fixed: the sample period is a number
            if not value.is_constant():
                self._err(v, f"{v['name']}: a parameter read by sample() must have a literal value (the interval "
                             f"and start are fixed when the model is translated)")
            self.env[("parameter", k)] = value
            return
        if value.numel() != 1:  # an array value rumoca gives a one-element (or empty) declaration
            if value.numel() > 1:
                self._err(v, f"{v['name']}: a value of {value.numel()} elements for a scalar")
            self.env[("parameter", k)] = value
            return
        if not value.is_constant() or self._scalar(v) != "real":
            # computed from others, or a Boolean/Integer (structural: it selects equations): not settable
            self.env[("parameter", k)] = value
            return
        unit, text = self._doc(v, "parameter")
        lo, hi = self._constant(a.get("min"), v, "min"), self._constant(a.get("max"), v, "max")
        default = float(ca.evalf(value))
        self.env[("parameter", k)] = b.param(v["name"], default, unit, text,
                                             lower=-math.inf if lo is None else lo, upper=math.inf if hi is None else hi)
        self.param_values[self.env[("parameter", k)].name()] = default
        self.param_syms.append(self.env[("parameter", k)])

    def _refuse_flat(self) -> None:
        """What the token scan cannot see (e.g. a construct reached through an extends)."""
        self.chains: list[list[tuple]] = []  # the when/elsewhen chains: each branch's condition span (source, start)
        self.clocked = set()  # the parameters sample()'s arguments read: rumoca fixes the period at their values
        for chain in self.flat.get("when_chains") or []:
            branches = [chain.get("first", {})] + list(chain.get("else_when") or [])
            if len(branches) > 1:
                spans = []
                for br in branches:
                    cond = br.get("condition") or {}
                    body = next(iter(cond.values())) if isinstance(cond, dict) and cond else {}
                    span = body.get("span") if isinstance(body, dict) else None
                    spans.append(((span or {}).get("source"), (span or {}).get("start")))
                self.chains.append(spans)
            for br in branches:
                for call in _find(br.get("condition"), "BuiltinCall"):
                    if call.get("function") == "Sample":
                        self.clocked.update(ref["name"]["name"] for ref in _find(call.get("args"), "VarRef"))

    def _residuals(self) -> list[tuple[ca.SX, int | None]]:
        out = []
        top_flows = {self.vars[fl["flow"]]["name"] for fl in self._connectors()}
        for op in self.st["continuous_equation_operations"]:
            (kind, body), = op.items()
            origin = (body.get("provenance") or {}).get("origin")
            if isinstance(origin, dict) and origin.get("generated") == "flow_balance_equation" and kind == "residual" \
                    and {x.name() for x in ca.symvar(self.graph(body["residual"]))} <= top_flows:
                continue  # "flow = 0" of an unconnected top-level connector: here a flange bonds it
            span = (body.get("provenance") or {}).get("span") or {}
            line = self._offset_line(span.get("start"))
            if kind == "structured":  # a for-equation: its bodies at each value of its binders
                out += [(e, line) for e in self._for_equation(body, line)]
                continue
            if kind != "residual":
                raise ModelicaError(self.filename, line, f"an equation of kind {kind!r} is not supported")
            self.units(body["residual"])  # raises at a unit mismatch
            out += [(e, line) for e in _elements(self.graph(body["residual"]))]
        return out

    def _for_equation(self, body: dict, line: int | None) -> list[ca.SX]:
        """The scalar residuals of a structured (for-) equation: each body at each combination of
        its domain's binder values."""
        domains = self.st.get("domains", [])
        dom = domains[body["domain"]] if body.get("domain") is not None and body["domain"] < len(domains) else None
        if dom is None or dom.get("parent") is not None:
            raise ModelicaError(self.filename, line, "a nested for-equation is not supported yet")
        if body.get("scalar_view") == "RowMajorProjection":  # an array equation: every element of its body
            return [e for node in body["bodies"] for e in _elements(self.graph(node))]
        binders = dom["domain"]["binders"]
        ranges = [range(bd["lower"], bd["upper"] + 1, bd.get("step") or 1) for bd in binders]
        out = []
        for values in product(*ranges):
            env = {**self.env, **{("binder", (body["domain"], k)): ca.SX(float(v)) for k, v in enumerate(values)}}
            g = dataclasses.replace(self.graph, env=env)
            out += [e for node in body["bodies"] for e in _elements(g(node))]
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
        the solved unknowns (key -> expression) and the choice per flange.  Where no choice
        does, the states tied by a constraint (an index-2 system, e.g. two masses joined rigidly,
        or a spring's relative position that fixes a mass's one) are reduced first
        (:meth:`_reduce_index`).  A flange whose other causality the equations do not allow gets
        the reason in ``fl["why"]`` (the bond check names it when a partner needs that other one)."""
        both, options = [], []
        for fl in flanges:  # effort_out: the potential is given (an input); flow_out: the flow is given
            both.append([("effort_out", ("algebraic", fl["potential"])), ("flow_out", ("algebraic", fl["flow"]))])
            stated = self.causality.get(fl["name"])  # a scene's choice
            options.append([o for o in both[-1] if o[0] == stated] if stated else both[-1])
        unknown_flanges = sorted(set(self.causality) - {fl["name"] for fl in flanges})
        if unknown_flanges:
            raise ModelicaError(self.filename, None, f"causality of {unknown_flanges[0]!r}: the model has no such "
                                                     f"flange (flanges: {', '.join(fl['name'] for fl in flanges) or 'none'})")
        choices = list(product(*options)) if flanges else [()]
        for reduce in (False, True):
            for choice in choices:
                found = self._determined(b, residuals, unknown, choice, reduce)
                if found is None:
                    continue
                rows, keys, res = found
                for i, fl in enumerate(flanges):
                    other = next(o for o in both[i] if o != choice[i])
                    fl["why"] = self._refused(b, residuals, unknown, choice[:i] + (other,) + choice[i + 1:], flanges)
                subst = self._inputs_for(b, flanges, choice, unknown)
                r = ca.substitute(res, ca.vertcat(*subst.keys()), ca.vertcat(*subst.values())) if subst else res
                return self._sorted_solve(r, keys, unknown, rows), choice
        if self.causality:  # the stated causality is refused with the reason, when the other would do
            stated = tuple(opts[0] for opts in options)
            why = self._refused(b, residuals, unknown, stated, flanges) or "they would not determine its variables"
            names = ", ".join(f"{fl['name']}: {c}" for fl, (c, _) in zip(flanges, stated) if fl["name"] in self.causality)
            raise ModelicaError(self.filename, None, f"causality {names}: the equations do not allow it: {why}")
        n_eq = len(residuals)
        raise ModelicaError(self.filename, None, f"the equations do not determine the model's variables: {n_eq} "
                                                 f"equations for {len(unknown) - len(flanges)} unknowns (states' "
                                                 f"derivatives, outputs and other variables; connectors counted with "
                                                 f"one of their two variables given)"
                                                 + (f"; {self.index_problem}" if self.index_problem else ""))

    def _determined(self, b: BlockBuilder, residuals, unknown: dict, choice, reduce: bool, rates: dict | None = None):
        """``(rows, keys, residual)`` when the equations determine the unknowns with each flange's
        variable of ``choice`` given (states tied by constraints demoted first when ``reduce``,
        which adds them to ``unknown``; ``rates``: given positions whose rates are known too, see
        :meth:`_reduce_index`), else None."""
        given = {key for _, key in choice}
        keys = [k for k in unknown if k not in given]
        rows = list(residuals)
        if reduce:
            rows, keys = self._reduce_index(b, rows, keys, unknown, rates)
            if rows is None:
                return None
        res = ca.vertcat(*[r for r, _ in rows]) if rows else ca.SX(0, 1)
        if len(keys) != res.numel():
            return None
        w = ca.vertcat(*[unknown[k] for k in keys]) if keys else ca.SX(0, 1)
        if keys and ca.sprank(ca.jacobian_sparsity(res, w)) < len(keys):
            return None
        return rows, keys, res

    def _refused(self, b: BlockBuilder, residuals, unknown: dict, choice, flanges: list[dict]) -> str:
        """Why the equations do not determine the unknowns under ``choice`` ("" when they do):
        the index problem :meth:`_reduce_index` names, else the count.  A position flange taking
        the rate counts as a position whose derivative is that rate (the constraint on it
        differentiated once)."""
        rates = {unknown[key].name(): (unknown[key], ca.SX.sym(f"{fl['name']}.v"))
                 for fl, (c, key) in zip(flanges, choice) if c == "effort_out" and fl["position"]}
        kept = self.index_problem
        self.index_problem = ""
        try:
            if any(self._determined(b, residuals, dict(unknown), choice, r, rates) is not None for r in (False, True)):
                return ""
            return self.index_problem or "the equations would not determine the model's variables"
        finally:
            self.index_problem = kept

    index_problem = ""
    causality: dict = {}  # flange name -> the causality a scene states (translate's causality)
    _PRIORITY = {"Never": 0, "Avoid": 1, "Default": 2, "Prefer": 3, "Always": 4}

    def _reduce_index(self, b: BlockBuilder, rows: list, keys: list, unknown: dict, rates: dict | None = None):
        """Demote states tied by constraints until the equations determine the unknowns: a row
        that the equations leave free of unknowns, ``g(x) = 0``, makes one of its states (the
        one without a fixed start, then the lowest ``stateSelect``, the last declared) an unknown, and its time
        derivative ``dg/dx . der(x) = 0`` is added (the dummy-derivative method on the
        constraint as the equations give it).  ``rates``: symbol name -> (position, its rate) of
        given positions whose rate is known (a position flange taking its partner's velocity):
        a constraint may tie a state to them, and its derivative reads the rate.  Returns
        ``(rows, keys)``, or ``(None, None)`` with :attr:`index_problem` saying why not (a
        constraint through an input, whose derivative the block does not have)."""
        rates = rates or {}
        keys = list(keys)
        rows = list(rows)
        states = [key[1] for key in unknown if key[0] == "derivative"]
        for _ in range(len(states) + 1):
            res = ca.vertcat(*[r for r, _ in rows]) if rows else ca.SX(0, 1)
            w = ca.vertcat(*[unknown[k] for k in keys]) if keys else ca.SX(0, 1)
            if len(keys) == res.numel() and ca.sprank(ca.jacobian_sparsity(res, w)) == len(keys):
                return rows, keys
            free = self._constraints(res, keys, unknown)
            if not free:
                return None, None
            g, line = free[0], None
            live = [k for k in states if ("state", k) not in keys]
            tied = [k for k in live if ca.depends_on(g, self.env[("state", k)])]
            own = {self.env[("state", j)].name() for j in states} | {sym.name() for _, sym in b._params} | \
                {sym.name() for sym in self.mode_syms.values()} | {self.time.name()}
            own |= {self.env[("parameter", j)].name() for j in range(len(self.vars))
                    if ("parameter", j) in self.env and self.env[("parameter", j)].is_symbolic()} | set(rates)
            inputs = [s for s in ca.symvar(g) if s.name() not in own]
            if inputs or not tied:
                self.index_problem = (f"the states are tied by the constraint 0 = {_short(g)}"
                                      + (f", which involves {inputs[0].name()}, an input or a variable the "
                                         f"partner gives (its derivative is not known to the block)"
                                         if inputs else ""))
                return None, None
            k = min(tied, key=lambda j: (self._fixed(j), self._PRIORITY.get(
                self.vars[j]["attributes"].get("state_select") or "Default", 2), -j))
            unknown[("state", k)] = self.env[("state", k)]
            keys.append(("state", k))
            xs = ca.vertcat(*[self.env[("state", j)] for j in states], *[pos for pos, _ in rates.values()])
            xd = ca.vertcat(*[unknown[("derivative", j)] for j in states], *[rate for _, rate in rates.values()])
            rows.append((ca.jtimes(g, xs, xd), line))
        return None, None

    def _fixed(self, k: int) -> bool:
        """Whether state ``k`` has a start value that must hold (``fixed = true``): such a state
        is kept, so the demoted one starts where the constraint puts it."""
        fixed = self.vars[k]["attributes"].get("fixed")
        return bool(fixed and all(fixed)) if isinstance(fixed, list) else bool(fixed)

    def _constraints(self, res: ca.SX, keys: list, unknown: dict) -> list:
        """The rows of ``res = 0`` left free of unknowns (and not identically zero) after
        solving, one at a time, the rows linear in a single unknown: constraints among the
        states (and parameters, inputs)."""
        rows = [res[i] for i in range(res.numel())]
        out: list = []
        self._eliminate(rows, {k: unknown[k] for k in keys}, None, out)
        return out

    def _eliminate(self, rows: list, pending: dict, lines: list | None, free: list | None = None) -> dict:
        """Solve, one at a time in row order, the rows linear in a single pending unknown,
        substituting each solution into the other rows (``rows`` and ``pending`` are updated in
        place; returns the solved unknowns).  A row left without unknowns must be zero: else it
        is appended to ``free`` (a constraint) or, without ``free``, refused with its line."""
        names = {sym.name(): k for k, sym in pending.items()}
        deps = [{x.name() for x in ca.symvar(r)} & names.keys() for r in rows]
        solved: dict = {}
        solved_deps: dict = {}
        progress = True
        while pending and progress:
            progress = False
            for i, r in enumerate(rows):
                if r is None:
                    continue
                if not deps[i]:
                    rows[i] = None
                    if not (r.is_zero() or (free is not None and ca.simplify(r).is_zero())):
                        if free is None:
                            raise ModelicaError(self.filename, lines[i] if lines else None,
                                                "this equation is redundant or contradicts the others")
                        free.append(r)
                    continue
                if len(deps[i]) != 1:
                    continue
                (nm,) = deps[i]
                key = names[nm]
                sym = pending[key]
                coef = ca.jacobian(r, sym)
                if ca.depends_on(coef, sym):
                    continue
                value = -ca.substitute(r, sym, ca.SX(0)) / coef
                del pending[key], names[nm]
                rows[i] = None
                vdeps = {x.name() for x in ca.symvar(value)} & names.keys()
                for j, q in enumerate(rows):
                    if q is not None and nm in deps[j]:
                        rows[j] = ca.substitute(q, sym, value)
                        deps[j] = (deps[j] - {nm}) | vdeps
                for k2 in solved:
                    if nm in solved_deps[k2]:
                        solved[k2] = ca.substitute(solved[k2], sym, value)
                        solved_deps[k2] = (solved_deps[k2] - {nm}) | vdeps
                solved[key], solved_deps[key] = value, vdeps
                progress = True
                break
        if free is not None:  # the rows the eliminated unknowns leave without any
            for i, r in enumerate(rows):
                if r is not None and not deps[i]:
                    rows[i] = None
                    if not ca.simplify(r).is_zero():
                        free.append(r)
        return solved

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
        solved = self._eliminate(rows, pending, lines)
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
        if fl.get("why"):
            takes = "the velocity" if causality == "flow_out" else "the force"
            fl["why"] = f"taking {takes} in leaves an index problem: {fl['why']}"
        if causality == "effort_out":  # potential in, effort (force on the partner = -f) out
            unit, text = self._doc(fv, "connector variable")
            b.output(fv["name"], -value[fl["flow"]], unit, f"on the partner: -{fv['name']} of the model, whose flow "
                                                           f"variable is the {text}")
            flow = f"{name}.v" if fl["position"] else pv["name"]
            b.flange(name, fv["name"], flow, "effort_out", why=fl.get("why", ""))
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
                b.flange(name, fv["name"], f"{name}.v", "flow_out", why=fl.get("why", ""))
            else:
                b.output(pv["name"], value[fl["potential"]], unit, text)
                b.flange(name, fv["name"], pv["name"], "flow_out", why=fl.get("why", ""))


__all__ = ["translate", "front_end", "unsupported", "ModelicaError", "DAE_SCHEMA", "INTEGRATORS"]
