"""The part map on the dashboard: the publisher keeps a live map, the API serves stored
and live maps, and in a real browser (Debian's chromium driven by Playwright) the map of a
live job print appears and fills in, and a stored print's map is drawn.

Servers run as child processes (``ajtwin dashboard``) on 127.0.0.1 and a free port and are
stopped by their PID; every wait is bounded. Screenshots go to ``$AJTWIN_SCREENSHOT_DIR``
when set (docs/figures/part_map/).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import pytest

from ajtwin.web.publisher import LivePublisher
from ajtwin.web.server import CHROMIUM, DashboardProcess, launch_chromium, layout_faults

PROGRAM = Path("tests/data/prg/prg2svg/2 and 6-Au.prg").resolve()
TIMEOUT_MS = 120_000


def test_publisher_keeps_the_live_part_map_for_pages_opened_later():
    pub = LivePublisher()
    assert pub.part_snapshot("vm") is None
    pub.open_part("vm", {"program": "p.prg", "outline": {"x": [0, 1], "y": [0, 0]}})
    pub.publish_part("vm", {"portions": {"index": [0, 1], "p_out": [0.1, float("nan")]},
                            "points": {"portion": [0, 1], "x": [0, 1], "y": [0, 0]}})  # fmt: skip
    pub.publish_part("vm", {"portions": {"index": [2], "p_out": [0.9]},
                            "points": {"portion": [2], "x": [2], "y": [0]},
                            "alarms": [{"alarm": 1, "cause": "nozzle_clog"}]})  # fmt: skip
    snap = pub.part_snapshot("vm")
    assert snap["program"] == "p.prg" and snap["portions"]["index"] == [0, 1, 2]
    assert snap["portions"]["p_out"] == [0.1, None, 0.9]  # strict JSON for the page
    assert snap["points"]["x"] == [0, 1, 2] and snap["alarms"][0]["cause"] == "nozzle_clog"
    # a new live print of the machine starts a new map
    pub.open_part("vm", {"program": "q.prg", "outline": {"x": [], "y": []}})
    assert pub.part_snapshot("vm")["portions"] is None
    with pytest.raises(ValueError, match="dict"):
        pub.publish_part("vm", [1, 2])


playwright_api = pytest.importorskip("playwright.sync_api")
browser_only = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="run `make chromium`")


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    folder = tmp_path_factory.mktemp("screenshots")
    yield folder
    target = os.environ.get("AJTWIN_SCREENSHOT_DIR")
    if target:
        Path(target).mkdir(parents=True, exist_ok=True)
        for png in folder.glob("*.png"):
            shutil.copy(png, Path(target) / png.name)


@pytest.fixture(scope="module")
def job_registry(tmp_path_factory):
    """'lab1' printed the public program for 6 min (clog from 3 min), ingested with its job
    and a tolerance; 'lab2' printed without a job; 'lab3' the same print with its job but no
    tolerance."""
    from ajtwin.apps.quality.part_map import Tolerance
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.print_job import job_entry
    from ajtwin.simulation import run_job_print, simulate
    from ajtwin.store.registry import Registry

    folder = tmp_path_factory.mktemp("registry")
    record = run_job_print(
        PROGRAM, "nozzle_clog", 1, duration_min=6.0, overrides={"fault": {"onset_min": 3}}
    ).record
    width = float(record.data["true_linewidth_um"].median())
    store = folder / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("lab1")
    reg.add_machine("lab2")
    entry = job_entry(PROGRAM, record, tolerance=Tolerance(width - 1.0, width + 1.0))
    ingest_record(reg, "lab1", record, source="job print", job=entry)
    ingest_record(reg, "lab2", simulate("exp1", seed=2, duration_min=2.0), source="plain")
    reg.add_machine("lab3")
    ingest_record(reg, "lab3", record, source="job print", job=job_entry(PROGRAM, record))
    reg.close()
    return {"store": store, "record": record, "tolerance": (width - 1.0, width + 1.0)}


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        context = launch_chromium(p)
        context.set_default_timeout(TIMEOUT_MS)
        yield context
        context.close()


def _page(browser):
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    return page, errors


@browser_only
def test_stored_print_part_map_is_drawn_from_the_api(job_registry, browser, tmp_path, shots):
    with DashboardProcess(job_registry["store"], log_path=tmp_path / "s.log") as dash:
        status, body = dash.get("api/machine/lab1/print/1/part", timeout=120.0)
        assert status == 200
        part = json.loads(body)
        assert part["program"] == PROGRAM.name and part["live"] is False
        n = len(part["portions"]["index"])
        assert n > 100 and len(part["points"]["x"]) >= 2 * n
        assert part["summary"]["flagged_portions"] == sum(part["portions"]["flagged"])
        # another tolerance through the query; a bad one is a sentence, HTTP 422
        status, body = dash.get("api/machine/lab1/print/1/part?tolerance=40:200", timeout=120.0)
        assert status == 200 and sum(json.loads(body)["portions"]["flagged"]) == 0
        status, body = dash.get("api/machine/lab1/print/1/part?tolerance=wide")
        assert status == 422 and "cannot read the tolerance" in json.loads(body)["error"]
        status, body = dash.get("api/machine/lab2/print/1/part")
        assert status == 404 and "stored without its job" in json.loads(body)["error"]
        status, _ = dash.get("api/machine/lab1/part/live")
        assert status == 404

        page, errors = _page(browser)
        try:
            page.goto(dash.page_url("/machine/lab1"))
            page.wait_for_function(
                "window.__ajtwin.part && window.__ajtwin.part.kind === 'print' "
                "&& window.__ajtwin.part.portions > 0",
                timeout=TIMEOUT_MS,
            )
            shown = page.evaluate("window.__ajtwin.part")
            assert shown["portions"] == n and shown["flagged"] == sum(part["portions"]["flagged"])
            names = page.evaluate("document.getElementById('plot-part').data.map(t => t.name)")
            assert "part (program)" in names and "printed: L_w − target" in names
            assert any(name.startswith("flagged") for name in names)
            assert "alarm raised (nozzle there)" in names  # the clog's alarm on the part
            # the box shows the stored tolerance, not a placeholder
            lo, hi = job_registry["tolerance"]
            box = page.locator("#part-tolerance").input_value()
            assert box == f"{float(f'{(lo + hi) / 2:.4g}'):g}±{float(f'{(hi - lo) / 2:.3g}'):g}"
            # flagged portions keep their colour: a thin ring over the point, no black mass
            traces = page.evaluate(
                "document.getElementById('plot-part').data.map(t => ({name: t.name, "
                "symbol: t.marker && t.marker.symbol, width: t.line && t.line.width, "
                "rim: t.marker && t.marker.line && t.marker.line.width}))"
            )
            ring = next(t for t in traces if t["name"].startswith("flagged"))
            assert ring["symbol"] == "circle-open" and ring["rim"] <= 1
            assert all(not t["width"] or t["width"] <= 1 for t in traces)
            printed = next(t for t in traces if t["name"].startswith("printed"))
            assert not printed["rim"]  # no black rim over the printed colour
            # the colour bar's title is clear of the chart's toolbar
            assert _overlap(page, "#plot-part .cbtitle", "#plot-part .modebar") == 0
            page.screenshot(path=shots / "machine_part_map.png", full_page=True)
            assert layout_faults(page) == []

            # without a tolerance: coloured by L_w, and the page says none is set
            page.goto(dash.page_url("/machine/lab3"))
            page.wait_for_function(
                "window.__ajtwin.part && window.__ajtwin.part.portions > 0", timeout=TIMEOUT_MS
            )
            names = page.evaluate("document.getElementById('plot-part').data.map(t => t.name)")
            assert "printed: L_w (no tolerance set)" in names
            assert not any(n.startswith("flagged") for n in names)
            assert "no tolerance set" in page.locator("#part-status").inner_text()
            assert page.locator("#part-tolerance").input_value() == ""

            # a print stored without its program: one line, no empty box
            page.goto(dash.page_url("/machine/lab2"))
            page.wait_for_function("window.__ajtwin.drawnPrint === 1")
            page.wait_for_function(
                "document.getElementById('part-status').textContent.includes('without its program')"
            )
            assert page.locator("#plot-part").bounding_box() is None  # not laid out
            assert page.locator("#part-section").bounding_box()["height"] < 150
            assert layout_faults(page) == []
        finally:
            page.close()
        assert not errors, errors


def _overlap(page, a: str, b: str) -> float:
    """The area [px²] two elements' boxes share on the page (0: apart)."""
    return page.evaluate(
        """([a, b]) => {
          const p = document.querySelector(a).getBoundingClientRect();
          const q = document.querySelector(b).getBoundingClientRect();
          const w = Math.min(p.right, q.right) - Math.max(p.left, q.left);
          const h = Math.min(p.bottom, q.bottom) - Math.max(p.top, q.top);
          return Math.max(w, 0) * Math.max(h, 0);
        }""",
        [a, b],
    )


@pytest.fixture(scope="module")
def live_job_print_work_s():
    """The live job print's twin, detectors and part map run once here first, so the server
    finds their compiled programs in the persistent cache (the same AJTWIN_CACHE_DIR) instead
    of compiling them against the page's clock; returns the wall time of a warm run [s]."""
    from ajtwin.apps.quality.part_map import parse_tolerance
    from ajtwin.engine.replay import VirtualPrintFeed

    feed = VirtualPrintFeed(None, "vm-job", "nozzle_clog", seed=1, minutes=4, onset_min=2,
                            job=PROGRAM, tolerance=parse_tolerance("74+-1.5"))  # fmt: skip
    feed.prepare()  # compiles (on an empty cache, however long that takes) and fills the cache
    t0 = time.monotonic()
    feed.prepare()
    return time.monotonic() - t0


@browser_only
def test_live_job_print_part_map_appears_and_fills_in(
    job_registry, browser, tmp_path, shots, live_job_print_work_s
):
    # every wait is bounded by the work it waits on: the server's run of the twin (warmed
    # above) and the replay of 4 min of samples at 25 samples/s
    start_ms = 1000 * (10 * live_job_print_work_s + 30)
    replay_ms = 1000 * (10 * 4 * 60 / 25 + 30)
    args = ["--virtual-print", "nozzle_clog", "--virtual-machine", "vm-job",
            "--virtual-minutes", "4", "--virtual-onset", "2", "--virtual-rate", "25",
            "--virtual-wait", str(start_ms / 1000), "--job", str(PROGRAM),
            "--tolerance", "74+-1.5"]  # fmt: skip
    log = tmp_path / "s.log"
    with DashboardProcess(job_registry["store"], extra_args=args, log_path=log) as dash:
        page, errors = _page(browser)
        try:
            page.goto(dash.page_url("/machine/vm-job"))
            page.wait_for_function(
                "window.__ajtwin.part && window.__ajtwin.part.kind === 'live' "
                "&& window.__ajtwin.part.portions > 0",
                timeout=start_ms,
            )
            first = page.evaluate("window.__ajtwin.part.portions")
            # it fills in: more portions are drawn as the print goes on, without a reload
            page.wait_for_function(
                f"window.__ajtwin.part.portions > {first} + 50", timeout=replay_ms
            )
            page.wait_for_function(
                "document.getElementById('plot-part').data.some("
                "t => t.name === 'alarm raised (nozzle there)')",
                timeout=replay_ms,
            )
            later = page.evaluate("window.__ajtwin.part")
            assert later["draws"] >= 2 and later["portions"] > first
            status, body = dash.get("api/machine/vm-job/part/live")
            snapshot = json.loads(body)
            assert status == 200 and snapshot["tolerance_um"] == [72.5, 75.5]
            assert len(snapshot["portions"]["index"]) >= later["portions"]
            markers = page.evaluate(
                "document.getElementById('plot-part').data"
                ".find(t => t.name === 'printed: L_w − target').marker"
            )
            assert markers["colorbar"]["title"]["text"] == "L_w − target [µm]"
            page.screenshot(path=shots / "machine_part_map_live.png", full_page=True)
        finally:
            page.close()
        assert not errors, errors
