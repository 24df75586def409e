"""No C source inside a Python string in cosim/: C lives in .c and .h files, where the compiler's
warnings, C tools and ``duplicates`` see it (generated declarations come from tables, a line at a
time).  A string is C when three or more of its lines are C: a preprocessor directive, or a
declaration or statement (a C type or ``return`` first, ``;`` or ``{`` last, a comment aside);
HTML, CSS, JavaScript and YAML in strings are not C."""
from __future__ import annotations

import ast
import re
from pathlib import Path

COSIM = Path(__file__).resolve().parents[1] / "cosim"
_TYPE = r"(static|const|typedef|volatile|extern|unsigned|void|int|double|float|char|bool|size_t|struct|enum|return|\w+_t)"
_C_LINE = re.compile(r"^\s*#\s*(include|define|ifn?def|endif|if|pragma)\b"
                     rf"|^\s*{_TYPE}\b.*[;{{]\s*(/\*.*\*/)?\s*$")


def c_lines(text: str) -> int:
    return sum(bool(_C_LINE.search(line)) for line in text.splitlines())


def c_strings(source: str) -> list[int]:
    """Line numbers of the string literals (f-strings joined) of ``source`` that hold C."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value
        elif isinstance(node, ast.JoinedStr):
            text = "".join(v.value for v in node.values if isinstance(v, ast.Constant) and isinstance(v.value, str))
        else:
            continue
        if c_lines(text) >= 3:
            found.append(node.lineno)
    return found


def test_the_detector_finds_c_in_a_string():
    fake = 'SOURCE = r"""\n#include <stdint.h>\nint f(int x) {\n    return x;\n}\n"""\n'
    assert c_strings(fake) == [1]
    assert c_strings('DOC = """Prose; with a semicolon.\nAnd {braces} in text.\n"""\n') == []
    css_js = 'PAGE = """body { margin: 0; }\nh1 { color: #222; }\nvar x = 1;\nfunction f(a) {\n  return a;\n}\n"""\n'
    assert c_strings(css_js) == []


def test_no_c_source_in_python_strings_in_cosim():
    offenders = [f"{p.relative_to(COSIM.parent)}:{line}" for p in sorted(COSIM.rglob("*.py"))
                 for line in c_strings(p.read_text())]
    assert not offenders, f"C source in Python strings (move it to a .c/.h file): {offenders}"
