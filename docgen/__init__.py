"""Documentation helpers: the reference pages generated from the code (:mod:`docgen.reference`)
and the mkdocs hook that adds them at build time (:mod:`docgen.hooks`).  The check of the figures
quoted in the pages is ``benchmarks/figures.py --check``."""
