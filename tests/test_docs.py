"""The docs a user reads: self-contained, linked correctly, current, not a lab notebook.

Pins: no page refers to a file outside the repository or carries work-diary wording; every
relative link and anchor resolves; every figure under docs/figures is shown by some page;
history (before/after narratives, dates of work, rounds) stays a small share of the text.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
CLI_PAGE = DOCS / "reference" / "cli.md"  # generated from the code's help texts
PAGES = sorted(DOCS.rglob("*.md")) + [ROOT / "README.md"]
TEXT_FILES = sorted(
    p for p in DOCS.rglob("*") if p.suffix in {".md", ".json", ".sh", ".csv", ".txt", ".toml"}
) + [ROOT / "README.md"]
FIGURE_SUFFIXES = {".png", ".svg", ".jpg", ".jpeg", ".gif"}

#: Wording that belongs to the project's work, not to its users. "session" is allowed only as
#: the registry's *live session* (a print followed by `ajtwin live`, table `live_sessions`).
FORBIDDEN = {
    "a file outside the repository": re.compile(r"\.\./shared|\bshared/SPEC|SPEC\.md"),
    "a work session": re.compile(r"(?<!live )(?<!live_)(?<!live-)\bsessions?\b", re.I),
    "an agent": re.compile(r"\bagents?\b", re.I),
    "a helper": re.compile(r"\bhelpers?\b", re.I),
    "a load average": re.compile(r"\bload[ _]average|\bload\s*(≈|~)?\s*\d", re.I),
    "an issue number": re.compile(r"\bissues?\s*#?\d+", re.I),
}
#: The model is documented in the repository (docs/reference/model.md), cited as "model
#: reference §N"; the old working note's name must not appear in hand-written pages.
SPEC_WORD = re.compile(r"\bSPEC\b")
DOCS_PATH = re.compile(r"\bdocs/[\w./-]+\.md\b")

LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def _prose(text: str) -> str:
    """Markdown without code blocks and inline code (links there are examples, not links)."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, blanks → hyphens."""
    text = heading.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    anchors = set()
    for line in FENCE.sub("", page.read_text(encoding="utf-8")).splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        slug = _slug(match.group(1))
        n = seen.get(slug, 0)
        anchors.add(slug if n == 0 else f"{slug}-{n}")
        seen[slug] = n + 1
    return anchors


def _links(page: Path):
    """(target path or None for this page, anchor or '') of every relative link of a page."""
    for target in LINK.findall(_prose(page.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        yield ((page.parent / path).resolve() if path else None), anchor


@pytest.mark.parametrize("path", TEXT_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_carry_no_reference_outside_the_repository_and_no_work_diary_wording(path):
    text = path.read_text(encoding="utf-8")
    found = [
        f"{what}: {m.group(0)!r}"
        for what, pattern in FORBIDDEN.items()
        for m in pattern.finditer(text)
    ]
    if path.suffix == ".md" and path != CLI_PAGE:
        found += [f"the working note's name: {m.group(0)!r}" for m in SPEC_WORD.finditer(text)]
        found += [
            f"a docs path that does not exist: {m.group(0)!r}"
            for m in DOCS_PATH.finditer(text)
            if not (ROOT / m.group(0)).is_file()
        ]
    assert not found, f"{path.relative_to(ROOT)}: " + "; ".join(found)


def test_cli_reference_cites_no_working_note_and_no_missing_docs_page():
    text = CLI_PAGE.read_text(encoding="utf-8")
    stale = SPEC_WORD.findall(text) + [
        m.group(0) for m in DOCS_PATH.finditer(text) if not (ROOT / m.group(0)).is_file()
    ]
    assert not stale, stale


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_to_a_file_and_heading_that_exist(page):
    broken = []
    for target, anchor in _links(page):
        target_file = target or page.resolve()
        if not target_file.is_relative_to(ROOT):
            broken.append(f"{target_file}: outside the repository")
        elif not target_file.exists():
            broken.append(f"{target_file.relative_to(ROOT)}: no such file")
        elif anchor and target_file.suffix == ".md" and anchor not in _anchors(target_file):
            broken.append(f"{target_file.relative_to(ROOT)}#{anchor}: no such heading")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_every_figure_under_docs_figures_is_shown_by_a_page():
    shown = {target for page in PAGES for target, _ in _links(page) if target is not None}
    figures = [p.resolve() for p in (DOCS / "figures").rglob("*") if p.suffix in FIGURE_SUFFIXES]
    assert figures, "docs/figures holds no figure"
    unshown = sorted(str(p.relative_to(ROOT)) for p in figures if p not in shown)
    assert not unshown, "figures no page shows (delete them or show them): " + ", ".join(unshown)


#: What marks a block of text as history: dates of work, rounds and passes, before/after
#: narratives, "was … now", "re-measured", "no longer", "what changed". A heuristic that
#: over-counts (it also flags "before the twin runs" or a measurement date), so the share it
#: gives is an upper bound.
HISTORY = re.compile(
    r"""\b20\d\d-\d\d-\d\d\b | \bround\s\d\b | \b(first|second|third|fourth)\s+pass\b |
    \bbefore\b[^\n]*\bafter\b | \bafter\b[^\n]*\bbefore\b | \bwas\b[^.\n]*\bnow\b |
    \(was\s | \bno\s+longer\b | \bre-?measured\b | \bre-?run\b | \bpreviously\b |
    \bused\s+to\b | \bsince\s+(the|issue|20|round) | \b(morning|evening|night)\b |
    \bwhat\s+changed\b | \bchanged\b | \bearlier\s+(version|default|run|figure)s?\b""",
    re.I | re.X,
)


def _blocks(text: str):
    """Paragraphs, list items, table rows and headings of a markdown text, as line lists."""
    block: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        starts = stripped.startswith(("|", "- ", "* ", "#")) or re.match(r"\d+\. ", stripped)
        if not stripped or starts:
            if block:
                yield block
            block = [line] if stripped else []
            if stripped.startswith(("|", "#")):
                yield block
                block = []
        else:
            block.append(line)
    if block:
        yield block


def history_share(pages) -> float:
    """Share of non-blank lines in sections that are history: a section whose heading carries a
    history marker, or 30 % or more of whose lines are in blocks that do."""
    total = history = 0
    for page in pages:
        sections = re.split(r"(?m)^(?=#)", page.read_text(encoding="utf-8"))
        for section in sections:
            lines = marked = 0
            for block in _blocks(section):
                n = sum(1 for line in block if line.strip())
                lines += n
                marked += n if HISTORY.search("\n".join(block)) else 0
            heading = section.splitlines()[0] if section.startswith("#") else ""
            total += lines
            if HISTORY.search(heading) or (lines and marked / lines >= 0.3):
                history += lines
    return history / total


def test_history_share_of_the_docs_stays_at_most_a_quarter():
    assert history_share(PAGES) <= 0.25


def test_history_share_counts_a_before_after_narrative_as_history(tmp_path):
    narrative = tmp_path / "n.md"
    narrative.write_text(
        "# Round 2\n\nThe filter was slow; now it is fast.\n\n"
        "# Reference\n\nThe filter runs on scaled states.\n\nIt reports the NIS.\n",
        encoding="utf-8",
    )
    # the Round 2 section (heading + 1 line) is history, the Reference section (3 lines) not
    assert history_share([narrative]) == pytest.approx(2 / 5)
