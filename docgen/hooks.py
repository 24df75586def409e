"""The mkdocs hook of the documentation (``hooks:`` in mkdocs.yml): adds the reference pages
generated from the code (:data:`docgen.reference.PAGES`) to the build (in place of their
committed copies, so the site never shows a stale one), and puts every page of
``docs/`` that the nav does not name under "More topics", so that a page a contributor adds is
never left out of the site."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the project's packages, when mkdocs runs from another directory
    sys.path.insert(0, str(ROOT))

from docgen.reference import PAGES  # noqa: E402


def _named(nav) -> set[str]:
    out: set[str] = set()
    for item in nav or []:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        if isinstance(value, list):
            out |= _named(value)
        elif isinstance(value, str):
            out.add(value)
    return out


def on_config(config, **kwargs):
    docs = Path(config["docs_dir"])
    named = _named(config["nav"])
    extra = sorted(str(p.relative_to(docs)) for p in docs.rglob("*.md") if str(p.relative_to(docs)) not in named)
    extra = [p for p in extra if p not in PAGES]
    if extra and config["nav"] is not None:
        config["nav"].append({"More topics": extra})
    return config


def on_files(files, config, **kwargs):
    from mkdocs.structure.files import File

    for rel, page in PAGES.items():  # the committed copy replaced by what the code generates now
        committed = files.get_file_from_path(rel)
        if committed is not None:
            files.remove(committed)
        files.append(File.generated(config, rel, content=page()))
    return files
