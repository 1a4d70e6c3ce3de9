"""The dashboard in a real browser: Debian's chromium driven by Playwright.

Servers run as child processes (``ajtwin dashboard``) on 127.0.0.1 and a free port and
are stopped by their PID; every wait is bounded. Screenshots of each page are saved under
the test's temporary folder (and copied to ``$AJTWIN_SCREENSHOT_DIR`` when set, which is
how docs/dashboard/ was made).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from ajtwin.web.server import CHROMIUM, DashboardProcess, launch_chromium, layout_faults

playwright_api = pytest.importorskip("playwright.sync_api")
pytestmark = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="run `make chromium`")
TIMEOUT_MS = 120_000


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
def registry(tmp_path_factory):
    """A registry with a real twin run: 'lab1' printed 6 min with a nozzle clog from 3 min
    (virtual printer; the record file stays, so the truth is known), 'lab2' has no prints."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate
    from ajtwin.store.registry import Registry

    folder = tmp_path_factory.mktemp("registry")
    record = simulate(
        "nozzle_clog", seed=1, duration_min=6.0, overrides={"fault": {"onset_min": 3}}
    )
    path = folder / "lab1_print1.parquet"
    write_record(record, path)
    store = folder / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("lab1", notes="bench A")
    reg.add_machine("lab2")
    result = ingest_record(reg, "lab1", record, source=str(path))
    reg.close()
    assert result.events, "the virtual clog should have raised an alarm during ingest"
    return {"store": store, "record": record, "result": result}


@pytest.fixture(scope="module")
def server(registry, tmp_path_factory):
    log = tmp_path_factory.mktemp("server") / "dashboard.log"
    with DashboardProcess(registry["store"], log_path=log) as dash:
        yield dash


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        context = launch_chromium(p)
        context.set_default_timeout(TIMEOUT_MS)
        yield context
        context.close()


@pytest.fixture
def page(browser):
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    yield page
    page.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def test_fleet_page_lists_the_registry(server, registry, page, shots):
    from ajtwin.store.registry import Registry

    page.goto(server.page_url("/"))
    rows = page.locator("#fleet-rows tr")
    assert rows.count() == 2
    assert page.locator("#fleet-rows tr").nth(0).get_attribute("data-machine") == "lab1"
    lab1 = page.locator('tr[data-machine="lab1"]')
    lab2 = page.locator('tr[data-machine="lab2"]')
    assert lab1.get_attribute("data-status") == "alarm"
    assert "nozzle clog" in lab1.inner_text()
    # the headline fault in words and what to do about it on this machine
    assert "clean the nozzle, then `ajtwin machine maintain lab1 --nozzle-cleaned`" in (
        lab1.inner_text()
    )
    assert "no prints" in lab2.inner_text() and lab2.get_attribute("data-status") == "idle"
    # the state shown is the registry's end state (d_a, 4 significant digits)
    with Registry(registry["store"]) as reg:
        end = reg.last_print("lab1")["end_mean"]
    assert f"{end[0]:.4g} µm" in lab1.locator("td").nth(4).inner_text()
    assert lab1.locator("svg.spark").count() == 4  # a trend per key state
    # never commissioned nor maintained: the care column says so
    assert "not recorded" in lab1.locator("td").nth(8).inner_text()
    page.wait_for_function("document.getElementById('conn').classList.contains('up')")
    page.screenshot(path=shots / "fleet.png", full_page=True)
    assert layout_faults(page) == []  # at 1400 px: no overflow, clipped text, empty box


def test_machine_page_states_with_bands_and_truth(server, registry, page, shots):
    from ajtwin.store.registry import Registry

    page.goto(server.page_url("/machine/lab1"))
    page.wait_for_function("window.__ajtwin.drawnPrint === 1")
    traces = page.evaluate(
        "document.getElementById('plot-states').data.map(t => "
        "({name: t.name, fill: t.fill || null, x: t.x, y: t.y}))"
    )
    bands = [t for t in traces if t["fill"] == "tonexty"]
    truth = [t for t in traces if t["name"] == "truth (virtual printer)"]
    assert len(bands) == 5 and len(truth) == 5
    # the upper band of ΔR_N is x̂ + 2σ from the registry's arrays, at the plotted times
    with Registry(registry["store"]) as reg:
        arrays = reg.print_arrays(reg.last_print("lab1")["id"])
    t_min = np.asarray(bands[3]["x"], dtype=float)
    k = np.round(t_min * 60).astype(int)
    # (the registry may keep means/σ as float32: add them in float64 as the page does)
    expected = arrays["means"][k, 3].astype(float) + 2 * arrays["stds"][k, 3].astype(float)
    np.testing.assert_allclose(np.asarray(bands[3]["y"], dtype=float), expected, rtol=1e-12)
    # truth is the virtual printer's, read from the print's file
    np.testing.assert_allclose(
        np.asarray(truth[3]["y"], dtype=float), registry["record"].true_states[k, 3], rtol=1e-12
    )
    # detectors with thresholds; the stored alarm with its cause; the history
    detector_names = page.evaluate("document.getElementById('plot-detectors').data.map(t=>t.name)")
    assert "CUSUM P_c+P_s (h=16)" in detector_names and "windowed NIS (120 s)" in detector_names
    assert "nozzle clog" in page.locator("#alarms").inner_text()
    assert page.locator("#history tbody tr").count() == 1
    assert page.locator("#status").inner_text() == "alarm"
    # the model–machine guard's verdict stored at ingest is the one the page shows
    with Registry(registry["store"]) as reg:
        guard = reg.last_print("lab1")["summary"]["mismatch"]
    assert page.locator("#mismatch").count() == int(guard["mismatch"])
    if guard["mismatch"]:
        assert guard["message"] in page.locator("#mismatch").inner_text()
    assert page.locator("#calibration").count() == 0  # never commissioned
    # numbers as a person reads them: no e-notation on the cards or in the alarm table
    for where in ("#summary", "#alarms"):
        if page.locator(where).count():
            assert not re.search(r"\de[-+]?\d", page.locator(where).inner_text()), where
    # θ as drift rates in %/h, Q_m in nL/s: the units the CLI and the reports use
    titles = page.evaluate(
        "['plot-theta', 'plot-outputs'].map(id => { const l = document.getElementById(id)"
        ".layout; return Object.keys(l).filter(k => k.startsWith('yaxis'))"
        ".map(k => l[k].title.text); }).flat()"
    )
    assert "ΔR_N [%/h]" in titles and "Q_m [nL/s]" in titles, titles
    page.screenshot(path=shots / "machine.png", full_page=True)
    assert layout_faults(page) == []  # at 1400 px: no overflow, clipped text, empty box


def test_new_print_appears_without_reload(server, page):
    """The registry watcher pushes a print committed by another process to an open page."""
    page.goto(server.page_url("/machine/lab2"))
    page.wait_for_function("document.getElementById('conn').classList.contains('up')")
    page.evaluate("window.__notReloaded = true")
    from ajtwin.store.registry import NewPrint, Registry

    n = 30
    t = np.arange(n, dtype=float)
    means = np.tile([3.5, 1.0, 0.0, 0.02, 4.6e-7], (n, 1))
    stds = np.array([0.03, 0.003, 1e-3, 1e-3, 1e-8])
    with Registry(server.store) as reg:
        reg.save_print("lab2", NewPrint(
            content_hash="watcher-test", source="test", meta={}, summary={}, n_samples=n,
            duration_s=float(n), start_mean=means[0], start_cov=np.eye(5), end_mean=means[-1],
            end_cov=np.diag(stds**2), theta_before=np.zeros(5), theta_after=np.zeros(5),
            anomalies=[], arrays={"time_s": t, "means": means, "stds": np.tile(stds, (n, 1))},
        ), expected_last_seq=None)  # fmt: skip
    page.wait_for_function("window.__ajtwin.lastPrintEvent === 1", timeout=15_000)
    page.wait_for_function("window.__ajtwin.drawnPrint === 1", timeout=15_000)
    assert page.evaluate("window.__notReloaded") is True
    assert "#1" in page.locator("#history tbody").inner_text()


def test_whatif_forecast_and_advice(server, registry, page, shots):
    from ajtwin.apps.planning.forecast import Change, forecast, input_schedule
    from ajtwin.engine.start import machine_open_faults
    from ajtwin.engine.views import RegistryView

    page.goto(server.page_url("/whatif/lab1"))
    page.fill("#horizon", "10min")
    page.click("#run-forecast")
    page.wait_for_function("window.__ajtwin.forecastDrawn >= 1")
    traces = page.evaluate(
        "document.getElementById('plot-forecast').data.map(t => ({name: t.name, y: t.y}))"
    )
    mean_lw = np.asarray([t for t in traces if t["name"] == "forecast"][0]["y"], dtype=float)
    # the same numbers as the forecast function behind `ajtwin forecast`, called here
    view = RegistryView(registry["store"])
    twin, mean, cov, u_now, limits, _ = view.forecast_start("lab1")
    schedule = input_schedule(u_now, [Change(60.0, 1, 26.0)], 600)
    fc = forecast(twin, mean, cov, schedule)
    assert len(mean_lw) == 600
    np.testing.assert_allclose(mean_lw, fc.output_means[:, 0], rtol=1e-9)
    page.fill("#target", "70")
    _, open_fault = machine_open_faults(view.registry, "lab1")
    view.close()
    assert open_fault  # lab1's print clogged and nobody has cleaned the nozzle since
    page.click("#run-advise")
    # refused, as `ajtwin advise` refuses, until asked to advise all the same
    page.locator("#advise-error").wait_for(state="visible")
    refusal = page.locator("#advise-error").inner_text()
    assert refusal.startswith("not advising: print #1") and "clean the nozzle" in refusal
    page.check("#advise-anyway")
    page.click("#run-advise")
    page.wait_for_selector("#advice-table")
    advice = page.locator("#advice").inner_text()
    assert "on the target" in advice
    assert "advised with an open fault: nozzle clogging" in advice
    page.screenshot(path=shots / "whatif.png", full_page=True)
    assert layout_faults(page) == []  # at 1400 px: no overflow, clipped text, empty box


def test_bad_form_value_shows_a_message(server, page, shots):
    statuses = []
    page.on("response", lambda r: statuses.append(r.status) if "/api/" in r.url else None)
    page.goto(server.page_url("/whatif/lab1"))
    page.fill("#changes tr.change [name=value]", "60")
    page.click("#run-forecast")
    error = page.locator("#forecast-error")
    error.wait_for(state="visible")
    assert error.inner_text() == "change 1: Q_c 60 sccm is outside this machine's limits 15–35 sccm"
    page.fill("#target", "abc")
    page.click("#run-advise")
    page.locator("#advise-error").wait_for(state="visible")
    assert "target linewidth: 'abc' is not a number" in page.locator("#advise-error").inner_text()
    assert statuses.count(422) == 2 and 500 not in statuses
    page.screenshot(path=shots / "whatif_error.png", full_page=True)


def _wait_for_print_end(dash, machine: str, bound_s: float) -> None:
    """Poll /api/fleet until ``machine``'s live print has ended (bounded by ``bound_s``)."""
    deadline = time.monotonic() + bound_s
    while time.monotonic() < deadline:
        rows = {m["name"]: m for m in json.loads(dash.get("api/fleet")[1])["machines"]}
        live = rows.get(machine, {}).get("live") or {}
        if live and not live.get("printing"):
            return
        time.sleep(0.2)
    raise TimeoutError(f"{machine}'s live print did not end within {bound_s:.0f} s")


LIVE_PRINT = {"scenario": "nozzle_clog", "seed": 1, "minutes": 5, "onset_min": 3}


@pytest.fixture(scope="module")
def live_print_work_s():
    """The live print's twin and detectors run once here first, so the server finds their
    compiled programs in the persistent cache (the same AJTWIN_CACHE_DIR) instead of
    compiling them against the page's clock; returns the wall time of a warm run [s], the
    work the server does before its first sample."""
    from ajtwin.engine.replay import VirtualPrintFeed

    print_ = dict(LIVE_PRINT)
    feed = VirtualPrintFeed(None, "vm-live", print_.pop("scenario"), **print_)
    feed.prepare()  # compiles (on an empty cache, however long that takes) and fills the cache
    t0 = time.monotonic()
    feed.prepare()
    return time.monotonic() - t0


def test_live_clog_alarm_reaches_the_page(registry, browser, tmp_path, shots, live_print_work_s):
    """A live virtual print (twin + detectors) with a nozzle clog from 3 min: the alarm is
    on the page within seconds of the twin raising it, labelled as a clog, after the onset.
    A fleet page drawn while the print runs, whose socket opens only after the print ended,
    still says so: the rows are read again when the socket opens (on a slow first run the
    end used to fall between the page's rows and its socket, and the row said 'live'
    forever)."""
    minutes, rate = LIVE_PRINT["minutes"], 25  # the virtual print, its replay rate [samples/s]
    # every wait is bounded by the work it waits on: the server's run of the twin (its
    # programs warmed above, so loading them is all that is left of compiling) and the
    # replay of `minutes` of samples at `rate`
    start_ms = 1000 * (10 * live_print_work_s + 30)
    replay_ms = 1000 * (10 * minutes * 60 / rate + 30)
    args = ["--virtual-print", LIVE_PRINT["scenario"], "--virtual-machine", "vm-live",
            "--virtual-seed", str(LIVE_PRINT["seed"]), "--virtual-minutes", str(minutes),
            "--virtual-onset", str(LIVE_PRINT["onset_min"]), "--virtual-rate", str(rate),
            "--virtual-wait", str(start_ms / 1000)]  # fmt: skip
    with DashboardProcess(registry["store"], extra_args=args, log_path=tmp_path / "s.log") as dash:
        page, fleet = browser.new_page(), browser.new_page()
        held = []

        def hold(ws):  # the fleet page's socket opens against this stand-in, not the server
            held.append(ws)

        fleet.route_web_socket("**/ws", hold)
        try:
            page.goto(dash.page_url("/machine/vm-live"))  # a viewer: the print starts
            page.wait_for_function("window.__ajtwin.events > 5", timeout=start_ms)
            fleet.goto(dash.page_url("/"))  # drawn while the print runs ...
            row = fleet.locator('tr[data-machine="vm-live"]')
            assert "live print ended" not in row.inner_text()
            page.locator("#alarm-banner").wait_for(state="visible", timeout=replay_ms)
            shown = page.evaluate("window.__ajtwin.alarmsShown")
            assert shown and shown[0]["cause"] == "nozzle_clog"
            assert 180.0 < shown[0]["detected_s"] < 180.0 + 90.0  # after the true onset
            delay = shown[0]["shown_at"] - shown[0]["published_at"]
            assert 0.0 <= delay < 3.0, f"alarm took {delay:.2f} s from the twin to the page"
            banner = page.locator("#alarm-banner").inner_text()
            # the cause in words and what to do, the command naming this page's machine
            assert "likely cause: nozzle clogging: clean the nozzle, then `ajtwin machine" in banner
            assert "--nozzle-cleaned`" in banner
            # the "ready to print" card: this print's line never held still for the 2.5 min
            # the verdict needs before the clog moved it (the twin's verdict, computed apart:
            # never ready), so "not yet", with the twin's sentence as its title
            card = page.locator("#ready")
            assert card.locator(".big").inner_text() == "not yet"
            assert card.get_attribute("title").startswith("not settled yet: linewidth moving ")
            # states with bands were drawn live, and the page was never reloaded
            assert page.evaluate("document.getElementById('plot-states').data.length") == 20
            assert len(page.evaluate("window.__ajtwin.latencies")) > 10
            page.screenshot(path=shots / "machine_live.png", full_page=True)
            # the rest of the print is (5 min − the alarm's time) at `rate` samples/s: wait
            # for its end with a bound made of that work, not of a compilation's duration
            remaining_s = (minutes * 60 - shown[0]["detected_s"]) / rate
            _wait_for_print_end(dash, "vm-live", bound_s=10 * remaining_s + 30)
            # ... and its socket opens only now: nothing reached it, the row still says live
            assert held and fleet.evaluate("window.__ajtwin.events") == 0
            assert "live print ended" not in row.inner_text()
            for ws in held:
                ws.connect_to_server()
            # the page reads its rows again when its socket opens (one fetch): the row says
            # the print ended, and keeps the live-only machine's last ΔR_N, grown by the clog
            ended = fleet.locator('tr[data-machine="vm-live"]', has_text="live print ended")
            ended.wait_for(timeout=30_000)
            assert row.get_attribute("data-status") == "alarm"
            dr_n = float(row.locator("td").nth(6).locator(".val").inner_text().split()[0])
            assert dr_n > 0.04
            fleet.screenshot(path=shots / "fleet_live.png", full_page=True)
        finally:
            page.close()
            fleet.close()


def test_token_required(registry, tmp_path, browser):
    token = "t0ken-for-the-test"
    with DashboardProcess(registry["store"], token=token, log_path=tmp_path / "s.log") as dash:
        for path in ("", "api/fleet", "machine/lab1", "static/dashboard.js"):
            status, body = dash.get(path, token="")
            assert status == 401, path
        assert dash.get("api/fleet", token="wrong-token-value")[0] == 401
        status, body = dash.get("api/fleet")
        assert status == 200 and {m["name"] for m in json.loads(body)["machines"]} == {
            "lab1",
            "lab2",
        }
        page = browser.new_page()
        try:
            # without the token the browser gets 401; with it once, the cookie carries on
            assert page.goto(dash.url).status == 401
            assert page.goto(dash.page_url("/")).status == 200
            assert page.goto(dash.url + "machine/lab1").status == 200
            page.wait_for_function("document.getElementById('conn').classList.contains('up')")
        finally:
            page.close()
        # the websocket refuses a connection without the token, accepts one with it
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect

        url = dash.url.replace("http", "ws") + "ws"
        with pytest.raises(InvalidStatus, match="403"):
            with connect(url, open_timeout=10):
                pass
        with connect(
            url, open_timeout=10, additional_headers={"Authorization": f"Bearer {token}"}
        ) as ws:
            assert json.loads(ws.recv(timeout=10)) == {"type": "hello"}


@pytest.fixture(scope="module")
def commissioned_registry(tmp_path_factory):
    """'lab3': commissioned on its commissioning print (virtual machine seed 3), then its
    pressure gauges read 8 % high — the next print's model–machine guard fires."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.estimation.commission import commission
    from ajtwin.simulation import simulate
    from ajtwin.simulation.machine import MachineDeviation
    from ajtwin.store.calibration import save_calibration
    from ajtwin.store.registry import Registry

    store = tmp_path_factory.mktemp("commissioned") / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("lab3", notes="bench C")
    commissioning = simulate("commissioning", seed=41, duration_min=8.0, machine_seed=3)
    result = commission(commissioning)
    cal_id = save_calibration(reg, "lab3", result, "lab3_commissioning.parquet")
    gauges = MachineDeviation(name="gauges+8%", carrier_gauge_gain=1.08, sheath_gauge_gain=1.08)
    record = simulate(
        "exp1", seed=42, duration_min=6.0, continue_from=commissioning, machine=gauges
    )
    ingest = ingest_record(reg, "lab3", record, source="lab3_print1.parquet")
    reg.close()
    assert ingest.summary["mismatch"]["mismatch"], "the gauge error should trip the guard"
    return {"store": store, "calibration": result, "cal_id": cal_id, "guard": ingest.summary}


def test_machine_page_shows_calibration_and_mismatch(
    commissioned_registry, browser, tmp_path, shots
):
    """The commissioned machine's page: the active calibration card (the fitted values) and
    the model–machine mismatch card — one short line in words, coloured as a notice, said
    once, the guard's reasons on demand; the fleet row says it once too."""
    reg = commissioned_registry
    with DashboardProcess(reg["store"], log_path=tmp_path / "s.log") as dash:
        page = browser.new_page()
        errors = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        try:
            page.goto(dash.page_url("/machine/lab3"))
            page.wait_for_function("window.__ajtwin.drawnPrint === 1")
            card = page.locator("#calibration")
            assert f"active calibration {reg['cal_id']}" in card.inner_text()
            assert "lab3_commissioning.parquet" in card.inner_text()
            offset = reg["calibration"].calibration.linewidth_offset_um
            row = card.locator("tr", has_text="linewidth_offset_um")
            shown = float(row.locator("td").nth(1).inner_text())
            assert shown == pytest.approx(offset, rel=5e-4)  # 4 significant digits
            # the guard's verdict: one short line in words, as a notice (not the alarm's
            # red), said once on the page; its full reasons folded beneath, on demand
            guard = reg["guard"]["mismatch"]
            mismatch = page.locator("#mismatch")
            assert "print #1" in mismatch.inner_text()
            assert "carrier pressure" in mismatch.inner_text()
            assert guard["message"] not in mismatch.inner_text()  # folded
            assert guard["message"] in mismatch.locator("details").text_content()
            page_text = page.locator("main").inner_text()
            assert page_text.count("does not fit this machine") == 1, page_text
            said = mismatch.inner_text() + page.locator("#alarms").inner_text()
            assert "_Pa" not in said and "_um" not in said  # no raw variable names
            alarm_red = "rgb(198, 40, 40)"  # --alarm in dashboard.css
            colour = "e => getComputedStyle(e).color"
            assert mismatch.locator(".notice").evaluate(colour) != alarm_red
            page.screenshot(path=shots / "machine_calibration.png", full_page=True)
            page.goto(dash.page_url("/"))
            lab3 = page.locator('tr[data-machine="lab3"]')
            assert "last commissioned" in lab3.inner_text()
            shown = lab3.inner_text()
            assert "carrier pressure" in shown  # what the guard names, in words
            assert shown.count("does not fit this machine") == 1, shown
            assert "carrier_pressure_Pa" not in shown and guard["message"] not in shown
            assert len(lab3.locator("td").nth(1).inner_text().split()) <= 25
            assert lab3.locator(".cause").count() == 0  # nothing in the alarm's red
            assert lab3.locator(".notice").evaluate(colour) != alarm_red
            page.screenshot(path=shots / "fleet_mismatch.png", full_page=True)
        finally:
            page.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


@pytest.mark.slow
def test_machine_page_of_a_90_min_print(browser, tmp_path, shots):
    """A 90-min print with a nozzle clog from 60 min (docs/dashboard/machine_90min.png): the
    figures are decimated to at most MAX_POINTS points, the clog is found after its onset."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.views import MAX_POINTS
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate
    from ajtwin.store.registry import Registry

    record = simulate(
        "nozzle_clog", seed=3, duration_min=90.0, overrides={"fault": {"onset_min": 60}}
    )
    path = tmp_path / "lab9_print1.parquet"
    write_record(record, path)
    store = tmp_path / "r.sqlite"
    with Registry(store) as reg:
        reg.add_machine("lab9")
        result = ingest_record(reg, "lab9", record, source=str(path))
    clogs = [e for e in result.events if e.cause == "nozzle_clog"]
    assert clogs and 3600.0 <= clogs[0].detected_s <= 3600.0 + 300.0
    with DashboardProcess(store, log_path=tmp_path / "s.log") as dash:
        page = browser.new_page()
        try:
            page.goto(dash.page_url("/machine/lab9"))
            page.wait_for_function("window.__ajtwin.drawnPrint === 1")
            n = page.evaluate("document.getElementById('plot-states').data[2].x.length")
            assert 100 < n <= MAX_POINTS
            assert "nozzle clog" in page.locator("#alarms").inner_text()
            page.screenshot(path=shots / "machine_90min.png", full_page=True)
        finally:
            page.close()
