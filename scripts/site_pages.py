"""Pages of the documentation site made at build time (run by mkdocs-gen-files, `make docs`).

* **The Python API reference**: a page for every public module of ``src/ajtwin`` (no part
  of its dotted name starts with ``_``), found in the package tree at each build, so a
  module that is added or moves is covered without editing anything;
  ``reference/api/SUMMARY.md`` is its navigation (mkdocs-literate-nav).
* **The repository's root pages** (CHANGELOG.md, CONTRIBUTING.md) as site pages, their
  ``docs/…`` links made relative to the site; the docs pages' links to them follow.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"
DOCS = ROOT / "docs"
API = Path("reference/api")
#: repository file → its page on the site
ROOT_PAGES = {"CHANGELOG.md": "changelog.md", "CONTRIBUTING.md": "contributing.md"}


def public_modules(src: Path = SRC) -> list[tuple[str, ...]]:
    """The dotted names (as parts) of every public module and package under ``src``."""
    names = set()
    for path in (src / "ajtwin").rglob("*.py"):
        parts = path.relative_to(src).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if not any(part.startswith("_") for part in parts):
            names.add(parts)
    return sorted(names)


def api_pages() -> None:
    nav = mkdocs_gen_files.Nav()
    for parts in public_modules():
        page = Path(*parts).with_suffix(".md")
        nav[parts] = page.as_posix()
        with mkdocs_gen_files.open(API / page, "w") as f:
            f.write(f"::: {'.'.join(parts)}\n")
    with mkdocs_gen_files.open(API / "SUMMARY.md", "w") as f:
        f.writelines(nav.build_literate_nav())


def root_pages() -> None:
    for source, page in ROOT_PAGES.items():
        text = re.sub(r"\]\(docs/", "](", (ROOT / source).read_text(encoding="utf-8"))
        for other, other_page in ROOT_PAGES.items():
            text = text.replace(f"]({other}", f"]({other_page}")
        with mkdocs_gen_files.open(page, "w") as f:
            f.write(text)
    # the docs' own pages link to the repository file (right on GitHub): on the site, the page
    for path in sorted(DOCS.rglob("*.md")):
        name = path.relative_to(DOCS).as_posix()
        text = path.read_text(encoding="utf-8")
        depth = name.count("/")
        new = text
        for source, page in ROOT_PAGES.items():
            up = "../" * (depth + 1)
            new = new.replace(f"]({up}{source}", f"]({posixpath.join('../' * depth, page)}")
        if new != text:
            with mkdocs_gen_files.open(name, "w") as f:
                f.write(new)


api_pages()
root_pages()
