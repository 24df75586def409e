"""``python -m docgen [OUT]``: write the generated reference pages under ``OUT`` (default
``docs``: the committed copies, which links in the repository reach; ``mkdocs build`` regenerates
them itself through :mod:`docgen.hooks`).  ``--check``: write nothing, list the pages that differ
from what the code generates (exit 1 if any)."""
from __future__ import annotations

import sys
from pathlib import Path

from .reference import PAGES, stale_pages


def main(argv: list[str]) -> int:
    check = "--check" in argv
    args = [a for a in argv if a != "--check"]
    out = Path(args[0] if args else Path(__file__).resolve().parents[1] / "docs")
    if check:
        stale = stale_pages(out)
        for rel in stale:
            print(f"{out / rel}: differs from what the code generates (python -m docgen {out} rewrites it)")
        return 1 if stale else 0
    for rel, page in PAGES.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(page())
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
