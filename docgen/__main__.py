"""``python -m docgen OUT``: write the generated reference pages into ``OUT`` (to read them;
``mkdocs build`` generates them itself through :mod:`docgen.hooks`)."""
from __future__ import annotations

import sys
from pathlib import Path

from .reference import PAGES


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "site-reference")
    for rel, page in PAGES.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(page())
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
