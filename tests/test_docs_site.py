"""The documentation site (`make docs`): built strict, every page and public module in it, its
search working, nothing loaded from the internet.

The site is built once for the file (``mkdocs build --strict``, as `make docs` runs it), into
a temporary folder: a broken link or anchor, a page left out of the navigation, a docstring
whose cross-reference does not resolve fails the build, and so this file.
"""

from __future__ import annotations

import functools
import http.server
import os
import re
import subprocess
import sys
import threading
import time
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
PACKAGE = ROOT / "src" / "ajtwin"

#: tag → the attributes by which a page makes the browser fetch something
LOADING_ATTRIBUTES = {
    "script": ("src",),
    "link": ("href",),  # stylesheets, icons, fonts, preloads
    "img": ("src", "srcset"),
    "iframe": ("src",),
    "source": ("src", "srcset"),
    "video": ("src", "poster"),
    "audio": ("src",),
    "embed": ("src",),
    "object": ("data",),
}
REMOTE = re.compile(r"^\s*(https?:)?//", re.I)
CSS_REMOTE = re.compile(r"""url\(\s*['"]?\s*(https?:)?//|@import\s+['"]?(https?:)?//""", re.I)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The built site's folder, and what the build printed."""
    out = tmp_path_factory.mktemp("site")
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1", "DISABLE_MKDOCS_2_WARNING": "true"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-4000:]
    print(f"strict build: {time.perf_counter() - t0:.1f} s")
    return out, log


def test_site_builds_strict_with_no_warning(site):
    _, log = site
    warnings = [line for line in log.splitlines() if re.search(r"\b(WARNING|ERROR)\b", line)]
    assert not warnings, "\n".join(warnings)


def test_every_docs_page_is_a_page_of_the_site(site):
    out, _ = site
    pages = [
        p.relative_to(DOCS) for p in DOCS.rglob("*.md") if p.relative_to(DOCS).parts[0] != "results"
    ]
    assert len(pages) >= 40
    missing = [str(p) for p in pages if not (out / p.with_suffix(".html")).is_file()]
    assert not missing, missing
    for generated in ("changelog.html", "contributing.html"):
        assert (out / generated).is_file(), generated


def test_api_reference_has_a_rendered_page_for_every_public_module(site):
    out, _ = site
    modules = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        parts = parts[:-1] if parts[-1] == "__init__" else parts
        if not any(part.startswith("_") for part in parts):
            modules.add(parts)
    assert ("ajtwin", "estimation", "filters") in modules and len(modules) > 150
    unrendered = []
    for parts in sorted(modules):
        page = out / "reference" / "api" / Path(*parts).with_suffix(".html")
        # the module's own heading: mkdocstrings rendered the module, not an empty page
        if not page.is_file() or f'id="{".".join(parts)}"' not in page.read_text("utf-8"):
            unrendered.append(".".join(parts))
    assert not unrendered, unrendered


def test_a_docstring_cross_reference_becomes_a_link_to_its_object(site):
    """``:class:`~ajtwin.model.limits.StateLimits``` in a docstring: a link on the site."""
    out, _ = site
    page = (out / "reference" / "api" / "ajtwin" / "engine" / "chain.html").read_text("utf-8")
    assert re.search(r'href="[^"]*model/limits\.html#ajtwin\.model\.limits\.StateLimits"', page)
    assert ":class:" not in page and ":func:" not in page


class _Loads(HTMLParser):
    def __init__(self):
        super().__init__()
        self.remote: list[str] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in LOADING_ATTRIBUTES.get(tag, ()) and value and REMOTE.match(value):
                self.remote.append(f"<{tag} {name}={value!r}>")
            if name == "style" and value and CSS_REMOTE.search(value):
                self.remote.append(f"<{tag} style={value!r}>")

    def handle_data(self, data):
        if CSS_REMOTE.search(data):
            self.remote.append(f"inline CSS: {CSS_REMOTE.search(data).group(0)}")


def test_no_page_loads_anything_from_the_internet(site):
    out, _ = site
    found = []
    for path in out.rglob("*.html"):
        parser = _Loads()
        parser.feed(path.read_text("utf-8"))
        found += [f"{path.relative_to(out)}: {what}" for what in parser.remote]
    for path in out.rglob("*.css"):
        match = CSS_REMOTE.search(path.read_text("utf-8"))
        if match:
            found.append(f"{path.relative_to(out)}: {match.group(0)}")
    assert not found, found[:20]


def test_the_site_served_locally_finds_pages_by_search_and_asks_nothing_of_the_internet(site):
    """In a real browser: the search box finds the tutorial's nozzle clog; every request the
    pages make goes to the local server."""
    from ajtwin.web.server import CHROMIUM, launch_chromium

    if not Path(CHROMIUM).exists():
        pytest.skip("run `make chromium`")
    from playwright.sync_api import sync_playwright

    out, _ = site
    handler = functools.partial(_QuietHandler, directory=str(out))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{server.server_address[1]}/"
    requests: list[str] = []
    try:
        with sync_playwright() as p:
            context = launch_chromium(p)
            try:
                page = context.new_page()
                page.on("request", lambda request: requests.append(request.url))
                page.goto(base + "index.html", timeout=20_000)
                page.fill("input.md-search__input", "nozzle clog", timeout=10_000)
                page.wait_for_selector(".md-search-result__item", timeout=10_000)
                titles = page.locator(".md-search-result__item").all_inner_texts()
                page.goto(base + "reference/api/ajtwin/estimation/filters.html", timeout=20_000)
                heading = page.locator("h1").first.inner_text(timeout=10_000)
            finally:
                context.close()
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)
    assert titles and any("clog" in t.lower() for t in titles), titles
    assert "ajtwin.estimation.filters" in heading
    elsewhere = [url for url in requests if not url.startswith(base)]
    assert not elsewhere, elsewhere


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        pass


def test_help_and_readme_point_to_the_built_site():
    from click.testing import CliRunner

    from ajtwin.cli import main

    help_text = CliRunner().invoke(main, ["--help"]).output
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for text in (help_text, readme):
        assert "make docs" in text and "site/index.html" in text
