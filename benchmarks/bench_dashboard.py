"""Figures of the browser dashboard (Debian chromium through Playwright; ~5 min).

    .venv/bin/asv run --python=same --bench bench_dashboard

* **Fleet page with 50 machines**: a registry of 50 machines, each with one 30-min print
  (the arrays of one real twin run, stored 50 times: the same bytes per print as real
  prints). The page is opened 6 times (first with an empty browser cache): time from
  navigation start to the load event and to DOM ready (the fleet page needs no plotly.js);
  and the server's time for the HTML alone (urllib, 10 requests).
* **Live latency**: a virtual print (nozzle clog) published by the in-process publisher,
  1 min of exp1 at 1 sample/s (real time) and 5 min with a clog from 3 min at 10 samples/s. The page
  stamps each sample when its plots have been extended (``Plotly.extendTraces`` returned):
  latency = that time − the time ``publish`` was called (same machine clock); also the
  part up to the page's message handler. Median, 95th percentile, maximum; and the alarm.

The twin's own time per sample is not part of this figure (the virtual-print feed runs the
twin before replaying; the live engine's step time is measured by its own benchmark).
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from ._figures import tracked


def make_fleet(store: Path, n_machines: int = 50) -> None:
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.simulation import simulate
    from ajtwin.store.registry import Registry

    reg = Registry(store)
    reg.add_machine("m00")
    record = simulate("exp1", seed=7, duration_min=30)
    ingest_record(reg, "m00", record)
    p = reg.last_print("m00")
    arrays = reg.print_arrays(p["id"])
    for k in range(1, n_machines):
        name = f"m{k:02d}"
        reg.add_machine(name)
        reg.save_print(
            name,
            content_hash=f"bench-{k}",
            source="bench copy of m00 print 1",
            meta=p["meta"],
            summary=p["summary"],
            n_samples=p["n_samples"],
            duration_s=p["duration_s"],
            start_mean=p["start_mean"],
            start_cov=p["start_cov"],
            end_mean=p["end_mean"],
            end_cov=p["end_cov"],
            theta_before=p["theta_before"],
            theta_after=p["theta_after"],
            arrays=arrays,
            anomalies=[],
            expected_last_seq=None,
        )
    reg.close()


def fleet_figures(store: Path, context) -> dict:
    from ajtwin.web.server import DashboardProcess

    out = {}
    with DashboardProcess(store) as dash:
        server_s = []
        for _ in range(10):
            t0 = time.perf_counter()
            status, body = dash.get("")
            server_s.append(time.perf_counter() - t0)
            assert status == 200 and body.count(b"<tr data-machine=") == 50
        page = context.new_page()
        load_ms, dom_ms = [], []
        for _ in range(6):
            page.goto(dash.page_url("/"), wait_until="load")
            assert page.locator("#fleet-rows tr").count() == 50
            timing = page.evaluate(
                "(() => { const n = performance.getEntriesByType('navigation')[0];"
                " return [n.loadEventEnd - n.startTime,"
                " n.domContentLoadedEventEnd - n.startTime]; })()"
            )
            load_ms.append(timing[0])
            dom_ms.append(timing[1])
        page.close()
    out["fleet_50_machines_page_load_ms_first"] = round(load_ms[0], 1)  # empty browser cache
    out["fleet_50_machines_page_load_ms_median_next5"] = round(statistics.median(load_ms[1:]), 1)
    out["fleet_50_machines_page_load_ms_max_next5"] = round(max(load_ms[1:]), 1)
    out["fleet_50_machines_dom_ready_ms_median"] = round(statistics.median(dom_ms), 1)
    out["fleet_50_machines_server_html_ms_median"] = round(1e3 * statistics.median(server_s), 1)
    return out


def live_figures(
    store: Path, context, rate_hz: float, minutes: float, label: str, scenario: str
) -> dict:
    """Latency of a virtual print replayed at ``rate_hz`` samples per second."""
    from ajtwin.web.server import DashboardProcess

    n = int(round(minutes * 60))
    args = ["--virtual-print", scenario, "--virtual-machine", "vm",
            "--virtual-minutes", f"{minutes:g}", "--virtual-onset", "3",
            "--virtual-rate", f"{rate_hz:g}", "--virtual-wait", "180"]  # fmt: skip
    with DashboardProcess(store, extra_args=args) as dash:
        page = context.new_page()
        page.goto(dash.page_url("/machine/vm"))
        # wait for the print's end (bounded: its length at this rate plus a margin)
        page.wait_for_function(
            f"window.__ajtwin.latencies.length >= {n - 10}",
            timeout=int(1e3 * (n / rate_hz + 240)),
            polling=500,
        )
        latencies = np.asarray(page.evaluate("window.__ajtwin.latencies"), dtype=float)
        arrivals = np.asarray(page.evaluate("window.__ajtwin.arrivals"), dtype=float)
        alarms = page.evaluate("window.__ajtwin.alarmsShown")
        page.close()
    out = {
        f"live_{label}_samples_measured": int(latencies.size),
        f"live_{label}_sample_to_page_ms_median": round(float(np.median(latencies)), 1),
        f"live_{label}_sample_to_page_ms_p95": round(float(np.percentile(latencies, 95)), 1),
        f"live_{label}_sample_to_page_ms_max": round(float(latencies.max()), 1),
        # of which: publisher → websocket → message handler in the page (no drawing)
        f"live_{label}_sample_to_browser_ms_median": round(float(np.median(arrivals)), 1),
        f"live_{label}_sample_to_browser_ms_p95": round(float(np.percentile(arrivals, 95)), 1),
    }
    if alarms:
        out[f"live_{label}_alarm_to_page_ms"] = round(
            1e3 * (alarms[0]["shown_at"] - alarms[0]["published_at"]), 1
        )
        out[f"live_{label}_alarm_cause"] = alarms[0]["cause"]
    return out


FLEET = {
    "fleet_50_machines_page_load_ms_first": "ms",
    "fleet_50_machines_page_load_ms_median_next5": "ms",
    "fleet_50_machines_dom_ready_ms_median": "ms",
    "fleet_50_machines_server_html_ms_median": "ms",
}
LIVE = {
    f"live_{label}_{figure}": "ms"
    for label in ("1Hz", "10Hz")
    for figure in (
        "sample_to_page_ms_median",
        "sample_to_page_ms_p95",
        "sample_to_page_ms_max",
        "sample_to_browser_ms_median",
        "alarm_to_page_ms",
    )
    if not (label == "1Hz" and figure == "alarm_to_page_ms")  # exp1 at 1 Hz has no alarm
}


@tracked({**FLEET, **LIVE})
class Dashboard:
    """The fleet page of 50 machines, and the live page of a replayed print (1 Hz real time,
    and 10 Hz with a nozzle clog), in Debian's chromium."""

    timeout = 1800

    def setup_cache(self):
        from playwright.sync_api import sync_playwright

        from ajtwin.web.server import CHROMIUM, launch_chromium

        if not Path(CHROMIUM).exists():
            raise NotImplementedError("no chromium: make chromium")
        folder = Path.cwd()
        store = folder / "fleet50.sqlite"
        make_fleet(store)
        figures = {}
        with sync_playwright() as p:
            context = launch_chromium(p, user_data_dir=folder / "profile")
            try:
                figures.update(fleet_figures(store, context))
                # real time (1 sample/s, as a printer logs) and 10x faster (the clog alarm)
                figures.update(live_figures(store, context, 1.0, 1.0, "1Hz", "exp1"))
                figures.update(live_figures(store, context, 10.0, 5.0, "10Hz", "nozzle_clog"))
            finally:
                context.close()
        return figures
