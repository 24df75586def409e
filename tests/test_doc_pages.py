"""The documentation as a clone of the repository has it (no mkdocs needed): every relative link
of README.md and docs/**/*.md reaches a file (and its anchor a heading of that file), the
generated reference pages are committed up to date (so that those links resolve in the
repository too), and no page sends the reader to material a clone does not have (the thesis's
equations are restated in docs/explanation/thesis.md)."""
from __future__ import annotations

import re
import unicodedata
from pathlib import Path

from docgen import reference

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def prose(text: str) -> str:
    """The page without its fenced blocks and inline code (a link quoted as code is no link)."""
    return _CODE.sub("", _FENCE.sub("", text))


def links(page: Path) -> list[str]:
    return [t for t in _LINK.findall(prose(page.read_text())) if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]


def slug(heading: str) -> str:
    """The anchor Python-Markdown's toc extension gives a heading (its default slugify)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading: its text
    text = unicodedata.normalize("NFKD", text.replace("`", "").replace("*", "")).encode("ascii", "ignore").decode()
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def anchors(page: Path) -> set[str]:
    out, seen = set(), {}
    for line in _FENCE.sub("", page.read_text()).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            s = slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}_{n}")
    return out


def dead_links(pages: list[Path]) -> list[str]:
    dead = []
    for page in pages:
        for target in links(page):
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                dead.append(f"{page.relative_to(ROOT)}: {target} (no file {path})")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                dead.append(f"{page.relative_to(ROOT)}: {target} (no heading '#{anchor}' in {path or page.name})")
    return dead


def test_every_relative_link_resolves_in_the_repository():
    assert len(PAGES) > 30 and sum(len(links(p)) for p in PAGES) > 100  # the pages and their links were found
    assert dead_links(PAGES) == []


def test_a_dead_link_and_a_dead_anchor_are_found(tmp_path):
    (tmp_path / "b.md").write_text("# B page\n\n## Step 2: run it\n")
    page = tmp_path / "a.md"
    page.write_text("[ok](b.md) [ok](b.md#step-2-run-it) [gone](c.md) [bad](b.md#step-3) `[code](x.md)`\n"
                    "```\n[fenced](y.md)\n```\n[web](https://example.org/x.md)\n")
    global ROOT
    saved, ROOT = ROOT, tmp_path
    try:
        dead = dead_links([page])
    finally:
        ROOT = saved
    assert dead == ["a.md: c.md (no file c.md)", "a.md: b.md#step-3 (no heading '#step-3' in b.md)"]


def test_the_generated_reference_pages_are_committed_up_to_date():
    """The tutorial links reference/models.md: the page is committed, and equal to what the code
    generates (``python -m docgen docs`` rewrites the five pages after a declaration changes)."""
    stale = reference.stale_pages(ROOT / "docs")
    assert stale == [], f"run `python -m docgen docs` to refresh {stale}"


def test_no_page_sends_the_reader_to_material_a_clone_lacks():
    """The thesis's equations and parameters are restated in docs/explanation/thesis.md: no page
    cites the spec's sections or ../shared as the place to read them."""
    bad = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in PAGES
           for i, line in enumerate(p.read_text().splitlines(), 1)
           if re.search(r"SPEC(\.md)?\s*§|\.\./shared/", line)]
    assert bad == []
    assert "## " in (ROOT / "docs" / "explanation" / "thesis.md").read_text()


def test_no_scene_or_shipped_source_cites_the_spec():
    """The scenes a reader opens beside the tutorial (their comments, their Modelica and Python
    blocks) and the packages' docstrings point at docs/explanation/thesis.md, not at a SPEC a
    clone does not have.  (The MSL's sources are a dependency found through ``modelica_path``,
    with a one-line message where absent: not a citation.)"""
    files = [*sorted((ROOT / "scenarios").rglob("*")), *[f for d in ("cosim", "models", "fmus", "hardware")
                                                        for f in sorted((ROOT / d).rglob("*.py"))]]
    bad = [f"{f.relative_to(ROOT)}:{i}: {line.strip()}" for f in files
           if f.is_file() and f.suffix in (".yaml", ".mo", ".py", ".csv", ".md")
           for i, line in enumerate(f.read_text(errors="replace").splitlines(), 1)
           if re.search(r"SPEC(\.md)?\s*§", line)]
    assert bad == []


def test_the_tutorial_prints_what_it_quotes(tmp_path, cache):
    """Issue 32, item 9: the tutorial's cheap steps (every step but the multibody build, the
    fidelity study, the batch and the rig) run in a copy of the scenes, in the page's order; each
    exits 0 and prints every line the page quotes, each figure within its last printed digit
    (``python -m docgen.tutorial --update`` rewrites the quotes that drift)."""
    import shutil

    from docgen import quoted, tutorial

    shutil.copytree(ROOT / "scenarios", tmp_path / "scenarios")
    printed = tutorial.run_steps(tutorial.PAGE, tmp_path, expensive=False, cache=cache)
    assert all(lines[-1] == "(exit status 0)" for lines in printed.values()), \
        {c: lines[-4:] for c, lines in printed.items() if lines[-1] != "(exit status 0)"}
    blocks = [b for b in quoted.quoted_blocks(tutorial.PAGE) if tutorial._quote_key(b[1]) in printed]
    assert len(blocks) >= 4 and all(dated for *_, dated in blocks)
    for lineno, command, body, _ in blocks:
        assert quoted.drifted(body, printed[tutorial._quote_key(command)]) == [], (lineno, command)
    # a figure one unit past its last digit is found; wall times and the hash are not compared
    lineno, command, body, _ = blocks[0]
    now = printed[tutorial._quote_key(command)]
    line = next(ln for ln in body if "estimated worst error" in ln)
    value = quoted.NUMBER.findall(line.split("error", 1)[1])[0]
    worse = line.replace(value, f"{float(value) + 2 * quoted.last_digit(value):.{len(value.split('.')[1])}f}", 1)
    assert [d[1] for d in quoted.drifted([worse], now)] == [worse]
    scene_line = next(ln for ln in now if ln.startswith("scene pid_step ["))
    assert quoted.drifted([re.sub(r"\[\w+\]", "[0123456789ab]", scene_line)], now) == []
