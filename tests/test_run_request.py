"""The run request (issue 29, item 4): no function in cosim/run/ takes more than six parameters,
and the public ``run()`` keeps its keywords, mapped onto :class:`cosim.run.execute.RunRequest`."""
from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from cosim.run import execute
from cosim.run.execute import RunRequest

RUN_DIR = Path(__file__).resolve().parents[1] / "cosim" / "run"
MAX_PARAMETERS = 6


def _parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Every parameter a function takes (``self``, ``*args`` and ``**kwargs`` count one each)."""
    a = fn.args
    return (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
            + (a.vararg is not None) + (a.kwarg is not None))


def _wide_functions(folder: Path) -> list[str]:
    wide = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _parameters(node) > MAX_PARAMETERS:
                wide.append(f"{path.name}:{node.lineno} {node.name} ({_parameters(node)})")
    return wide


def test_the_counter_counts_every_kind_of_parameter():
    tree = ast.parse("def f(a, /, b, *c, d, e=1, **f): pass\nclass K:\n    def m(self, x=2): pass")
    fns = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)]
    assert [_parameters(f) for f in fns] == [6, 2]
    # the same count as inspect's of a live function
    assert _parameters(next(n for n in ast.walk(ast.parse(inspect.getsource(execute.run)))
                            if isinstance(n, ast.FunctionDef))) == len(inspect.signature(execute.run).parameters)


def test_no_function_in_cosim_run_takes_more_than_six_parameters():
    assert _wide_functions(RUN_DIR) == []


def test_run_keywords_are_the_request_fields():
    req = RunRequest.of(["stop_time=1"], None, {"engine": "compiled", "trace_format": "parquet", "log": None})
    assert (req.override_list, req.engine, req.trace_format) == (["stop_time=1"], "compiled", "parquet")
    assert req.log("quiet") is None  # log=None is the quiet log, as before
    # a base request with the keywords set over it; its overrides kept when none are given
    base = RunRequest(overrides={"stop_time": 2}, cache_dir=Path("c"))
    again = RunRequest.of(None, base, {"max_trace_bytes": "1GB"})
    assert (again.override_list, again.cache_dir, again.max_trace_bytes) == ([("stop_time", 2)], Path("c"), "1GB")


def test_a_misspelt_run_keyword_is_refused_by_name():
    with pytest.raises(TypeError, match="out_dirr"):
        execute.run("no-such-scene.yaml", out_dirr="x")
