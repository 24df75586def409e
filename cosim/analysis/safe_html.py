"""The one way text reaches a report's HTML (issue 33): every string from a scene, an FMU, a
sidecar, a batch table or a trace goes through one of these, never into a page as it is.

- :func:`text`: HTML text and quoted attribute values (``&``, ``<``, ``>``, ``"``, ``'`` escaped).
- :func:`label`: a string Plotly draws (titles, legends, axis titles, hover text): Plotly renders a
  subset of HTML in them (``<a href>``, ``<b>``, ``<br>``) and decodes entities, so escaping
  ``&``, ``<`` and ``>`` shows the text as it is and renders none of it.
- :func:`script_json`: a value as JSON inside ``<script>``: ``<``, ``>``, ``&`` and the line
  separators U+2028/U+2029 written as ``\\u`` escapes, so no string can close the script
  (``</script>``), open a comment (``<!--``) or end a JavaScript line; NaN and infinities become
  ``null``.
- :func:`href`: a link target (a path or a ``file:`` URI) percent-encoded, so that no scheme
  (``javascript:``) can be read into it.
"""
from __future__ import annotations

import html
import json
import math
from urllib.parse import quote

_SCRIPT_ESCAPES = {"<": "\\u003c", ">": "\\u003e", "&": "\\u0026", "\u2028": "\\u2028", "\u2029": "\\u2029"}
_SCRIPT_TABLE = str.maketrans(_SCRIPT_ESCAPES)


def text(value) -> str:
    """``value`` as HTML text or a quoted attribute value."""
    return html.escape("" if value is None else str(value), quote=True)


def label(value) -> str:
    """``value`` as a Plotly string (module docstring): shown as it is, no markup rendered."""
    return html.escape("" if value is None else str(value), quote=False)


def _finite(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def script_json(obj) -> str:
    """``obj`` as JSON safe to place inside ``<script>...</script>`` (module docstring)."""
    return json.dumps(_finite(obj), allow_nan=False, ensure_ascii=False).translate(_SCRIPT_TABLE)


def href(path: str) -> str:
    """A link target for a report: a ``file:`` URI, or a path percent-encoded (``:`` too, so no
    scheme can be read into it)."""
    path = str(path)
    if path.startswith("file:///"):
        return "file://" + quote(path[len("file://"):], safe="/%")
    return quote(path, safe="/")


__all__ = ["href", "label", "script_json", "text"]
