"""Documentation helpers: reference pages generated from the code (:mod:`docgen.reference`), the
mkdocs hook that adds them at build time (:mod:`docgen.hooks`), and the check of quoted figures
(:mod:`docgen.figures`)."""
