"""Mutation testing of the numerical core: does the test suite notice a realistic bug?

Each mutant changes one thing in one of the core modules -- an arithmetic operator (``+`` and
``-``, ``*`` and ``/``), a comparison's boundary or sense (``<`` and ``<=``, ``==`` and ``!=``), a
number (``n -> n + 1`` for integers, ``x -> 10 x`` for floats, ``0 -> 1``), a sign, ``and``/``or``,
a ``not``; in the compiled loop's C source (``cosim/master/fastloop.py``) the same operators plus the
Gauss-Seidel index ``order[c] -> c``.  Every mutant is written into a scratch copy of the
repository, and the fast tests chosen for its module (:data:`TARGETS`) run against it with a
timeout.  A mutant is *killed* when a test fails (or the run times out), *survives* otherwise.

Lines of timing instrumentation (wall-clock statistics, which the benchmarks print and no test
can pin down) are not mutated.

Printed: per module and overall, mutants tried, killed, timed out, survived, and the mutation
score (killed / (tried - listed as equivalent)), then every survivor with its file, line and
change.  Survivors that cannot change any observable result are listed, with a one-line reason,
in ``benchmarks/mutation_equivalent.txt`` (matched by file, source line and change, so line
numbers may drift); a reason starting with ``untested:`` records a real change no test
exercises yet, which still counts as a survivor.

    nice python benchmarks/mutation.py                 # 80 mutants sampled over the core
    nice python benchmarks/mutation.py --max 0         # every mutant (hours)
    python benchmarks/mutation.py --list               # the mutants, without running them
    python benchmarks/mutation.py --only cosim/master/fastloop.py --max 20 --seed 3

The sample is drawn with a fixed seed (``--seed``), spread over the modules in proportion to
their mutants, so two runs of the same tree try the same mutants.
"""
from __future__ import annotations

import argparse
import ast
import copy
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EQUIVALENT = ROOT / "benchmarks" / "mutation_equivalent.txt"

#: module -> the tests that should notice its mutants (fast ones; the whole suite takes minutes)
TARGETS: dict[str, list[str]] = {
    "models/virtual_work.py": ["tests/test_virtual_work.py", "tests/test_blocks.py", "-k",
                               "(lagrange or virtual or rigid or power or energy or mass_matrix or table_7) "
                               "and not multibody"],
    "models/kinematics.py": ["tests/test_kinematics.py", "tests/test_virtual_work.py"],
    "models/integrators.py": ["tests/test_fmu_integrators.py"],
    "cosim/master/graph.py": ["tests/test_master.py"],
    "cosim/master/system.py": ["tests/test_master.py"],
    "cosim/master/algorithm.py": ["tests/test_master.py"],
    "cosim/master/algorithms/jacobi.py": ["tests/test_master.py"],
    "cosim/master/algorithms/gauss_seidel.py": ["tests/test_master.py"],
    "cosim/master/engine.py": ["tests/test_master.py"],
    "cosim/master/simulate.py": ["tests/test_master.py"],
    "cosim/master/fastloop.py": ["tests/test_master.py"],
}


# --- mutants -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mutant:
    """One change: ``path`` (relative to the root), its 1-based ``line``, the source line's text,
    a description, and how to make the mutated file (``site`` index for Python, character span
    and replacement for C)."""

    path: str
    line: int
    source: str
    change: str
    site: int = -1
    span: tuple[int, int] = (0, 0)
    repl: str = ""

    @property
    def key(self) -> str:
        return f"{self.path} | {self.source.strip()} | {self.change}"


_BINOP_SWAP = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult}
_CMP_SWAP = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq,
             ast.NotEq: ast.Eq, ast.In: ast.NotIn, ast.NotIn: ast.In, ast.Is: ast.IsNot, ast.IsNot: ast.Is}
_SYM = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">",
        ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=", ast.In: "in", ast.NotIn: "not in", ast.Is: "is",
        ast.IsNot: "is not", ast.And: "and", ast.Or: "or"}


def _new_number(v):
    if isinstance(v, int):
        return v + 1
    return 1.0 if v == 0 else v * 10


_SOURCES: dict[str, str] = {}


def source(path: str) -> str:
    """The module's text as it was when first read: mutants stay consistent with the scratch
    copy even if the working tree changes during a run."""
    if path not in _SOURCES:
        _SOURCES[path] = (ROOT / path).read_text()
    return _SOURCES[path]


class _Sites(ast.NodeTransformer):
    """Walks a module in a fixed order; numbers every mutable node; with ``apply`` set, mutates
    only that node.  Skips docstrings, ``raise`` and ``assert`` statements and type annotations."""

    def __init__(self, apply: int = -1):
        self.apply, self.n, self.found = apply, 0, []

    def _site(self, node, change: str) -> bool:
        i = self.n
        self.n += 1
        self.found.append((node.lineno, f"{change} @col {node.col_offset}"))
        return i == self.apply

    def visit_Raise(self, node):
        return node

    visit_Assert = visit_Raise

    def visit_AnnAssign(self, node):
        node.value = self.visit(node.value) if node.value is not None else None
        return node

    def visit_FunctionDef(self, node):
        node.body = [self.visit(s) for s in node.body]  # not the annotations or the defaults' types
        node.args.defaults = [self.visit(d) for d in node.args.defaults]
        node.args.kw_defaults = [self.visit(d) if d is not None else None for d in node.args.kw_defaults]
        return node

    def visit_BinOp(self, node):
        self.generic_visit(node)
        new = _BINOP_SWAP.get(type(node.op))
        if new and self._site(node, f"{_SYM[type(node.op)]} -> {_SYM[new]}"):
            node.op = new()
        return node

    def visit_AugAssign(self, node):
        self.generic_visit(node)
        new = _BINOP_SWAP.get(type(node.op))
        if new and self._site(node, f"{_SYM[type(node.op)]}= -> {_SYM[new]}="):
            node.op = new()
        return node

    def visit_Compare(self, node):
        self.generic_visit(node)
        for k, op in enumerate(node.ops):
            new = _CMP_SWAP.get(type(op))
            if new and self._site(node, f"{_SYM[type(op)]} -> {_SYM[new]}"):
                node.ops[k] = new()
        return node

    def visit_BoolOp(self, node):
        self.generic_visit(node)
        new = ast.Or if isinstance(node.op, ast.And) else ast.And
        if self._site(node, f"{_SYM[type(node.op)]} -> {_SYM[new]}"):
            node.op = new()
        return node

    def visit_UnaryOp(self, node):
        self.generic_visit(node)
        if isinstance(node.op, (ast.USub, ast.Not)):
            what = "-x -> x" if isinstance(node.op, ast.USub) else "not x -> x"
            if self._site(node, what):
                return node.operand
        return node

    def visit_Constant(self, node):
        v = node.value
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            new = _new_number(v)
            if self._site(node, f"{v!r} -> {new!r}"):
                return ast.copy_location(ast.Constant(new), node)
        return node

    def visit_Expr(self, node):  # docstrings and bare strings
        if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            return node
        return self.generic_visit(node)


#: lines left alone: the run's timing instrumentation (wall-clock statistics that no test can pin
#: down; the benchmarks print them) and the Python loop's chunking for Ctrl-C responsiveness
SKIP_LINE = re.compile(r"perf_counter|_ns\(\)|now_ns|TICK|slave_ns|master_ns|\.ns\b|t_start|tprev|chunk|stepping"
                       r"|acc\[i\] \+= tn - tp")


def python_mutants(path: str) -> list[Mutant]:
    text = source(path)
    lines = text.splitlines()
    sites = _Sites()
    sites.visit(ast.parse(text))
    return [Mutant(path, ln, lines[ln - 1], change, site=i) for i, (ln, change) in enumerate(sites.found)
            if not SKIP_LINE.search(lines[ln - 1])]


def python_mutated(path: str, site: int) -> str:
    tree = ast.parse(source(path))
    tr = _Sites(apply=site)
    tree = ast.fix_missing_locations(tr.visit(copy.deepcopy(tree)))
    return ast.unparse(tree) + "\n"


#: operators of the C loop worth flipping, and the Gauss-Seidel index
_C_RULES = [(r"order\[c\]", "c"), (r"(?<=[\w)\]]) \+ (?=[\w(])", " - "), (r"(?<=[\w)\]]) - (?=[\w(])", " + "),
            (r"(?<=[\w)\]]) \* (?=[\w(])", " / "), (r"(?<=[\w)\]]) / (?=[\w(])", " * "), (r" < ", " <= "),
            (r" <= ", " < "), (r" > ", " >= "), (r" >= ", " > "), (r" == ", " != "), (r" != ", " == "),
            (r"\+\+(?=[a-z])", "--"), (r"(?<![\w.])1(?![\w.])", "0"), (r"(?<![\w.])0(?![\w.x])", "1")]


def c_mutants(path: str) -> list[Mutant]:
    """Mutants of the C source held in the module's ``SOURCE = r\"\"\"...\"\"\"`` string, code lines
    only (no comments, preprocessor lines or declarations of types)."""
    text = source(path)
    start = text.index('SOURCE = r"""') + len('SOURCE = r"""')
    end = text.index('"""', start)
    out = []
    pos = start
    for raw in text[start:end].splitlines(keepends=True):
        code = raw.split("/*")[0].split("//")[0]
        skip = code.lstrip().startswith(("#", "typedef", "*")) or not code.strip() or SKIP_LINE.search(code)
        if not skip:
            for pat, repl in _C_RULES:
                for m in re.finditer(pat, code):
                    line = text.count("\n", 0, pos) + 1
                    out.append(Mutant(path, line, raw.rstrip("\n"),
                                      f"{m.group(0).strip()} -> {repl.strip()} (C) @col {m.start()}",
                                      span=(pos + m.start(), pos + m.end()), repl=repl))
        pos += len(raw)
    return out


def mutants_of(path: str) -> list[Mutant]:
    found = python_mutants(path)
    if path == "cosim/master/fastloop.py":
        found = found + c_mutants(path)
    return found


def mutated_text(m: Mutant) -> str:
    if m.site >= 0:
        return python_mutated(m.path, m.site)
    text = source(m.path)
    return text[:m.span[0]] + m.repl + text[m.span[1]:]


#: mutants always tried (the bugs issue 13 found surviving): (module, text in the line, change prefix)
ALWAYS = [("cosim/master/fastloop.py", "i = order[c];", "order[c] -> c"),
          ("models/integrators.py", "err <= 1.0", "1.0 -> 10.0")]


def sample(pool: dict[str, list[Mutant]], n: int, seed: int) -> list[Mutant]:
    """``n`` mutants (0: all): the :data:`ALWAYS` ones, then a seeded sample spread over the
    modules in proportion to their counts."""
    total = sum(len(v) for v in pool.values())
    if n <= 0 or n >= total:
        return [m for v in pool.values() for m in v]
    fixed = [m for v in pool.values() for m in v
             if any(m.path == p and t in m.source and m.change.startswith(c) for p, t, c in ALWAYS)]
    rng = random.Random(seed)
    out = list(fixed)
    for path, ms in pool.items():
        k = max(1, round((n - len(fixed)) * len(ms) / total))
        out += [m for m in rng.sample(ms, min(k, len(ms))) if m not in fixed]
    return out[:n]


# --- running -----------------------------------------------------------------------------------
def scratch_copy() -> Path:
    dst = Path(tempfile.mkdtemp(prefix="rpr-mutation-"))
    for name in ("models", "fmus", "cosim", "tests", "scenarios", "benchmarks", "pyproject.toml"):
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dst / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        elif src.exists():
            shutil.copy2(src, dst / name)
    return dst


def run_tests(repo: Path, path: str, timeout: float) -> tuple[str, float]:
    """``"passed"``, ``"failed"`` or ``"timeout"`` of the module's tests in ``repo``, and seconds."""
    env = dict(os.environ, PYTHONPATH=str(repo), RPR_COSIM_CACHE=str(repo / ".cache" / "fmus"),
               PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *TARGETS[path]]
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - t0
    return ("passed" if res.returncode == 0 else "failed"), time.perf_counter() - t0


def load_equivalent() -> dict[str, str]:
    """``key -> reason`` from :data:`EQUIVALENT` (lines ``file | source line | change | reason``)."""
    out = {}
    if EQUIVALENT.exists():
        for raw in EQUIVALENT.read_text().splitlines():
            if raw.strip() and not raw.startswith("#"):
                parts = [p.strip() for p in raw.split(" | ")]
                if len(parts) >= 4:
                    out[" | ".join(parts[:3])] = " | ".join(parts[3:])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max", type=int, default=80, help="mutants to try (0: all); default 80")
    ap.add_argument("--seed", type=int, default=13, help="sampling seed (default 13)")
    ap.add_argument("--only", action="append", choices=sorted(TARGETS), help="restrict to a module (repeatable)")
    ap.add_argument("--timeout", type=float, default=0.0,
                    help="seconds per mutant (default: 3x the module's clean run + 30 s)")
    ap.add_argument("--list", action="store_true", help="list the sampled mutants and stop")
    args = ap.parse_args(argv)
    paths = args.only or list(TARGETS)
    pool = {p: mutants_of(p) for p in paths}
    chosen = sample(pool, args.max, args.seed)
    print(f"{sum(len(v) for v in pool.values())} mutants in {len(paths)} modules; trying {len(chosen)} "
          f"(seed {args.seed})", flush=True)
    if args.list:
        for m in chosen:
            print(f"  {m.path}:{m.line}: {m.change:<22} {m.source.strip()[:70]}")
        return 0
    equivalent = load_equivalent()
    repo = scratch_copy()
    for p in paths:  # the modules exactly as the mutants were made from them
        (repo / p).write_text(source(p))
    try:
        budget = {}
        for p in sorted({m.path for m in chosen}):
            st, secs = run_tests(repo, p, timeout=1800)
            if st != "passed":
                print(f"the clean tree fails the tests of {p} ({st}): fix that first", file=sys.stderr)
                return 2
            budget[p] = args.timeout or 3 * secs + 30
            print(f"  clean run of the tests for {p}: {secs:.1f} s (timeout per mutant {budget[p]:.0f} s)",
                  flush=True)
        results = []
        for k, m in enumerate(chosen, 1):
            target = repo / m.path
            original = target.read_text()
            try:
                target.write_text(mutated_text(m))
                st, secs = run_tests(repo, m.path, budget[m.path])
            finally:
                target.write_text(original)
            results.append((m, st))
            mark = {"failed": "killed", "timeout": "killed (timeout)", "passed": "SURVIVED"}[st]
            print(f"[{k:3d}/{len(chosen)}] {mark:<16} {secs:6.1f} s  {m.path}:{m.line}: {m.change}", flush=True)
    finally:
        shutil.rmtree(repo, ignore_errors=True)
    report(results, equivalent)
    return 0


def is_equivalent(m: Mutant, equivalent: dict[str, str]) -> bool:
    """Listed with a reason that is not ``untested: ...``."""
    return m.key in equivalent and not equivalent[m.key].startswith("untested:")


def report(results, equivalent: dict[str, str]) -> None:
    print("\nmodule                   tried  killed  timeout  survived  equivalent  score")
    rows = sorted({m.path for m, _ in results}) + ["all"]
    for p in rows:
        rs = [(m, s) for m, s in results if p == "all" or m.path == p]
        killed = sum(s == "failed" for _, s in rs)
        tout = sum(s == "timeout" for _, s in rs)
        surv = [m for m, s in rs if s == "passed"]
        eq = sum(is_equivalent(m, equivalent) for m in surv)
        denom = len(rs) - eq
        score = (killed + tout) / denom if denom else 1.0
        print(f"{p:<24} {len(rs):5d}  {killed:6d}  {tout:7d}  {len(surv):8d}  {eq:10d}  {score:6.1%}")
    surv = [m for m, s in results if s == "passed"]
    if surv:
        print("\nsurvivors:")
        for m in surv:
            why = equivalent.get(m.key)
            tag = f"equivalent: {why}" if is_equivalent(m, equivalent) else (f"NOT KILLED, {why}" if why else "NOT KILLED")
            print(f"  {m.path}:{m.line}: {m.change}  [{m.source.strip()[:80]}]  -- {tag}")
        print(f"\nequivalence lines for {EQUIVALENT.relative_to(ROOT)} (file | source line | change | reason):")
        for m in surv:
            if m.key not in equivalent:
                print(f"  {m.key} | ")


if __name__ == "__main__":
    sys.exit(main())
