"""The reference pages of the documentation, generated from the code's own declarations so that
they cannot drift from what the program accepts:

- ``reference/cli.md``: every verb and sub-verb from its argparse parser (:func:`cosim.cli.build_parser`);
- ``reference/scene-format.md``: the scene keys the checkers accept (:mod:`cosim.scenario.keys`),
  the guard settings (:mod:`cosim.scenario.guard_settings`) and the enumerated values;
- ``reference/batch-format.md``: the batch keys (:mod:`cosim.batch.spec`), distributions, plot
  kinds and measures (:mod:`cosim.batch.metrics`);
- ``reference/models.md``: the model catalog, as ``rpr-cosim fmu show --markdown`` prints it
  (:func:`cosim.analysis.model_doc.catalog_markdown`);
- ``reference/algorithms.md``: every registered master algorithm and the options it declares
  (:class:`cosim.master.algorithm.AlgorithmOption`).

Each function returns the page's Markdown; :data:`PAGES` maps the page's path under ``docs/`` to
its function.  They are committed under ``docs/`` so that links to them resolve in the repository
too (``python -m docgen docs`` rewrites them; ``tests/test_docs.py`` fails while a committed page
differs from what the code generates), and the mkdocs hook (:mod:`docgen.hooks`) regenerates them
at build time.
"""
from __future__ import annotations

import argparse
import inspect
import math
from collections.abc import Callable, Mapping
from pathlib import Path

GENERATED = ("<!-- generated from the code by docgen/reference.py (`python -m docgen docs` rewrites it; the site "
             "build regenerates it): edit the declarations, not this page -->\n\n")


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table(header: tuple[str, ...], rows) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(out) + "\n"


def _keys_table(declared: Mapping[str, str]) -> str:
    return _table(("key", "meaning"), ((f"`{k}`", v) for k, v in declared.items()))


# --- the CLI -------------------------------------------------------------------------------------
def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _help_of(parser: argparse.ArgumentParser) -> dict[str, str]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return {a.dest: a.help or "" for a in action._choices_actions}
    return {}


def _argument_rows(parser: argparse.ArgumentParser):
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = ", ".join(f"`{o}`" for o in a.option_strings) or f"`{a.metavar or a.dest}`"
        if a.option_strings and a.nargs != 0:
            name += f" {a.metavar or (('{' + ','.join(map(str, a.choices)) + '}') if a.choices else a.dest.upper())}"
        default = "" if a.default in (None, argparse.SUPPRESS, False, []) or a.nargs == 0 else f"`{a.default}`"
        choices = f" (one of: {', '.join(map(str, a.choices))})" if a.choices and a.option_strings else ""
        yield name, (a.help or "") % vars(a) if a.help and "%(" in a.help else (a.help or "") + choices, default


def _parser_section(title: str, parser: argparse.ArgumentParser, summary: str, level: int) -> list[str]:
    parts = [f"{'#' * level} `{title}`", ""]
    if summary:
        parts += [summary[0].upper() + summary[1:] + ("." if not summary.endswith(".") else ""), ""]
    if parser.description and parser.description != summary:
        parts += [parser.description, ""]
    usage = parser.format_usage().replace("usage: ", "").strip()
    parts += ["```text", usage, "```", ""]
    rows = list(_argument_rows(parser))
    if rows:
        parts += [_table(("argument", "what", "default"), rows), ""]
    subs, helps = _subparsers(parser), _help_of(parser)
    for name, sub in subs.items():
        parts += _parser_section(f"{title} {name}", sub, helps.get(name, ""), level + 1)
    return parts


def cli_page() -> str:
    """Every verb (and sub-verb) of ``rpr-cosim`` with its usage and arguments."""
    from cosim.cli import build_parser

    parser = build_parser()
    parts = ["# Command line", "", GENERATED,
             "Every verb of `rpr-cosim` (also `python -m cosim`), read from its argparse parser. "
             "`rpr-cosim VERB --help` prints the same in the terminal. A user mistake is one line naming the "
             "file, line or argument, with exit code 2.", ""]
    helps = _help_of(parser)
    for name, sub in _subparsers(parser).items():
        parts += _parser_section(f"rpr-cosim {name}", sub, helps.get(name, ""), 2)
    return "\n".join(parts)


# --- the scene format ----------------------------------------------------------------------------
def scene_page() -> str:
    """The scene file's keys as the checkers declare them."""
    from cosim.master.algorithm import ALGORITHMS
    import cosim.master.algorithms  # noqa: F401  (registers every algorithm)
    from cosim.scenario import guard_settings, keys

    parts = ["# Scene format", "", GENERATED,
             "A scene is a YAML file (or an SSP archive). The checkers accept exactly the keys below; an unknown "
             "key is one line `file:line: error: unknown key ...` naming the closest valid key. "
             "See the [tutorial](../tutorial.md) for a scene built step by step.", "",
             "## Top level", "", _keys_table(keys.TOP), "",
             "## A component (`components: {NAME: ...}`)", "", _keys_table(keys.COMPONENT), "",
             "A component is a catalog block (`model`, optionally `fidelity`, `options`), an FMU file (`fmu`) or "
             "the rig (`hardware`). The models, fidelities, options and parameters are in the "
             "[model catalog](models.md).", "",
             "## The master (`master: {...}`)", "", _keys_table(keys.MASTER), "",
             _table(("setting", "values"), [
                 ("`master.algorithm`", ", ".join(f"`{a}`" for a in sorted(ALGORITHMS))),
                 ("`master.inputs`", ", ".join(f"`{v}`" for v in keys.INPUT_MODES)),
                 ("`master.engine`", ", ".join(f"`{v}`" for v in keys.ENGINES)),
                 ("`fmi` (component)", ", ".join(f"`{v}`" for v in keys.FMI_VERSIONS)),
             ]), "",
             "The options of each algorithm are in the [algorithms reference](algorithms.md).", "",
             "## Guards (`guards: {...}` or `guards: off`)", "",
             _table(("setting", "default", "values"),
                    [(f"`{k}`", f"`{v}`", ", ".join(f"`{a}`" for a in guard_settings.ACTIONS) if k in guard_settings.GUARDS
                      else "a positive number") for k, v in guard_settings.DEFAULTS.items()]), "",
             "What each guard watches is explained in [Physical guards](../explanation/guards.md).", "",
             "## Paths of `--set` and batch axes", "",
             "`rpr-cosim run SCENE --set PATH=VALUE` and a batch axis's `path` take the same paths: dotted keys "
             "of the scene (`master.step`, `components.pid1.params.Kp`, `components.mech.options.config`); a "
             "`*` in the component name sets every matching component (`components.pid*.params.Kp=40`). The "
             "value is YAML (`40`, `5e-4`, `linear`, `[1, 2]`).", ""]
    return "\n".join(parts)


# --- the batch format ----------------------------------------------------------------------------
def batch_page() -> str:
    """The batch file's keys as its checker declares them."""
    from cosim.batch import metrics, spec

    doc = inspect.getdoc(spec) or ""
    example = doc.split("::", 1)[1].split("\n\n", 2)[1] if "::" in doc else ""
    parts = ["# Batch format", "", GENERATED,
             "A batch file names a base scene and what to vary over it; `rpr-cosim batch FILE` runs it (see the "
             "[tutorial](../tutorial.md#5-a-batch)). It is checked like a scene, before anything runs.", "",
             "## Top level", "", _keys_table(spec.TOP), "",
             "## A grid or zip axis", "",
             "`NAME: [v1, v2, ...]` (the name is then the path), or a mapping:", "", _keys_table(spec.AXIS), "",
             "## Random samples (`random:`)", "", _keys_table(spec.RANDOM), "",
             _table(("dist", "parameters"), ((f"`{k}`", ", ".join(f"`{p}`" for p in v)) for k, v in spec.DIST_KEYS.items())),
             "",
             "## Metrics", "",
             "Per recorded signal, a list of measures or a mapping with the keys "
             + ", ".join(f"`{k}`" for k in spec.METRIC_KEYS) + ". Measures: "
             + ", ".join(f"`{m}`" for m in metrics.MEASURES) + ", and `{at: [t, ...]}`; "
             + ", ".join(f"`{m}`" for m in sorted(metrics.NEEDS_TARGET)) + " need a target.", "",
             "```text", (inspect.getdoc(metrics) or "").strip(), "```", "",
             "## Report plots (`report: {plots: [...]}`)", "",
             _table(("kind", "keys"), ((f"`{k}`", ", ".join(f"`{p}`" for p in v)) for k, v in spec.PLOT_KINDS.items())),
             ""]
    if example:
        parts += ["## Example", "", "```yaml", inspect.cleandoc(example), "```", ""]
    return "\n".join(parts)


# --- the model catalog ---------------------------------------------------------------------------
def models_page() -> str:
    """The catalog as ``rpr-cosim fmu show --markdown`` prints it."""
    from cosim.analysis import model_doc

    return "\n".join(["# Model catalog", "", GENERATED, model_doc.catalog_markdown()])


# --- the algorithms ------------------------------------------------------------------------------
def _plain(rst: str) -> str:
    """A docstring paragraph as one Markdown line (Sphinx roles and double backticks as code)."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", rst).replace("``", "`")
    return " ".join(text.split())


def _bound(v: float) -> str:
    return "" if isinstance(v, float) and math.isnan(v) else ("inf" if v == math.inf else f"{v:g}")


def algorithms_page() -> str:
    """Every registered master algorithm, its traits and the options it declares."""
    from cosim.master.algorithm import ALGORITHMS
    import cosim.master.algorithms  # noqa: F401  (registers every algorithm)

    parts = ["# Master algorithms", "", GENERATED,
             "`master.algorithm` picks one of these; `master.options` takes the options it declares (checked "
             "against name, bounds and unit, with the closest name for a typo). How they work and when to use "
             "which: [Algorithms](../explanation/algorithms.md), [Choose an algorithm](../how-to/choose-algorithm.md).",
             ""]
    for name in sorted(ALGORITHMS):
        cls = ALGORITHMS[name]
        module = inspect.getmodule(cls).__name__
        doc = _plain((inspect.getdoc(inspect.getmodule(cls)) or inspect.getdoc(cls) or "").split("\n\n")[0])
        traits = [t for t, on in (("steps slaves in sequence (Gauss-Seidel order)", getattr(cls, "sequential", False)),
                                  ("needs slaves that can roll back", getattr(cls, "needs_rollback", False)),
                                  ("solves algebraic loops", getattr(cls, "solves_algebraic_loops", False)))
                  if on]
        parts += [f"## `{name}`", "", f"{doc} (`{module}`)", ""]
        if traits:
            parts += ["Traits: " + "; ".join(traits) + ".", ""]
        options = list(getattr(cls, "options", ()) or ())
        if options:
            rows = []
            for o in options:
                choices = getattr(o, "choices", None)
                rows.append((f"`{o.name}`", f"`{o.default}`" if choices else f"`{o.default:g}`",
                             " / ".join(f"`{c}`" for c in choices) if choices else f"[{_bound(o.lower)}, {_bound(o.upper)}]",
                             o.unit or "-", o.description))
            parts += [_table(("option", "default", "range", "unit", "meaning"), rows), ""]
        else:
            parts += ["No options.", ""]
    return "\n".join(parts)


#: Generated page (path under docs/) -> the function writing it.
PAGES: dict[str, Callable[[], str]] = {
    "reference/cli.md": cli_page,
    "reference/scene-format.md": scene_page,
    "reference/batch-format.md": batch_page,
    "reference/models.md": models_page,
    "reference/algorithms.md": algorithms_page,
}


def stale_pages(docs: Path) -> list[str]:
    """The generated pages whose copy under ``docs`` is missing or differs from what the code
    generates now."""
    return [rel for rel, page in PAGES.items() if not (docs / rel).is_file() or (docs / rel).read_text() != page()]
