"""HTML of the dashboard's pages (server-rendered shells; plots are drawn by plotly.js).

The fleet table is rendered here in full (it must load fast for many machines and read
without JavaScript); machine and what-if pages are shells whose plots
``/static/dashboard.js`` fills from the JSON API. Everything is escaped with
:func:`html.escape`; no script or style comes from outside the server.
"""

from __future__ import annotations

import datetime as _dt
from html import escape
from pathlib import Path
from string import Template
from urllib.parse import quote

import numpy as np

TEMPLATES = Path(__file__).parent / "templates"


def _template(name: str) -> Template:
    return Template((TEMPLATES / name).read_text(encoding="utf-8"))


STATUS_TEXT = {
    "printing": "printing",
    "idle": "idle",
    "alarm": "alarm",
    "mismatch": "model–machine mismatch",
}


def _page(title: str, body: str, page: str, machine: str = "", plots: bool = True) -> str:
    # the fleet page draws no plotly figure: it skips the 4.8 MB script
    plotly = '<script src="/static/plotly.min.js"></script>\n' if plots else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{escape(title)} — ajtwin</title>
<link rel="stylesheet" href="/static/dashboard.css">
{plotly}<script src="/static/dashboard.js" defer></script>
</head>
<body data-page="{escape(page)}" data-machine="{escape(machine)}">
<header><a class="brand" href="/">ajtwin</a><nav><a href="/">Fleet</a></nav>
<span id="conn" class="conn" title="live connection to the server">○ connecting</span></header>
<main>
{body}
</main>
</body></html>"""


def machine_path(name: str) -> str:
    """A machine name as one URL path segment: percent-encoded (``/``, ``?``, ``#``, ``%``,
    spaces ...), then HTML-escaped for an attribute.

    >>> machine_path("aj 300/α?")
    'aj%20300%2F%CE%B1%3F'
    """
    return escape(quote(str(name), safe=""))


def sparkline(trend: dict | None, width: int = 96, height: int = 22) -> str:
    """An inline SVG line of a trend {"t": [...], "v": [...]} (no JavaScript needed)."""
    if not trend or not trend.get("v"):
        return ""
    v = np.array([np.nan if x is None else x for x in trend["v"]], dtype=float)
    t = np.array([np.nan if x is None else x for x in trend["t"]], dtype=float)
    ok = np.isfinite(v) & np.isfinite(t)
    if ok.sum() < 2:
        return ""
    v, t = v[ok], t[ok]
    span_t = max(t[-1] - t[0], 1e-12)
    lo, hi = float(v.min()), float(v.max())
    span_v = hi - lo if hi > lo else 1.0
    xs = (t - t[0]) / span_t * (width - 2) + 1
    ys = height - 1 - (v - lo) / span_v * (height - 2)
    points = " ".join(f"{x:.1f},{y:.1f}" for x, y in zip(xs, ys))
    return (
        f'<svg class="spark" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
        f'aria-label="trend"><polyline fill="none" stroke="currentColor" stroke-width="1.2" '
        f'points="{points}"/></svg>'
    )


def fmt(value, unit: str = "") -> str:
    """A number with 4 significant digits (φ_A in scientific notation) and its unit."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "—"
    value = float(value)
    tiny_or_huge = value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e5)
    text = f"{value:.3e}" if tiny_or_huge else f"{value:.4g}"
    return f"{text} {unit}".strip() if unit and unit != "–" else text


def duration(seconds: float) -> str:
    """``"45 s"``, ``"6 min"``, ``"2.5 h"``.

    >>> duration(30), duration(360), duration(9000)
    ('30 s', '6 min', '2.5 h')
    """
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _when(iso: str | None) -> str:
    if not iso:
        return "—"
    try:
        t = _dt.datetime.fromisoformat(iso)
    except ValueError:
        return escape(str(iso))
    return escape(t.strftime("%Y-%m-%d %H:%M UTC"))


def link_badge(link: dict) -> str:
    """The badge of a machine link's state (text from :func:`ajtwin.web.publisher.link_text`)."""
    state = str(link.get("state", ""))
    reason = link.get("reason") or link.get("url") or ""
    return (
        f'<span class="link {escape(state)}" title="{escape(str(reason))}">'
        f"{escape(str(link.get('text', '')))}</span>"
    )


def mismatch_html(mismatch: dict) -> str:
    """The model–machine guard's verdict as a notice: its one line in words, the print, and
    the guard's full reasons and fixes folded beneath (opened on demand)."""
    fixes = "".join(f"<li>{escape(str(f))}</li>" for f in mismatch.get("fixes") or [])
    return (
        f'<span class="notice mismatch-of">{escape(str(mismatch.get("line", "")))} '
        f'<span class="dim">(print #{mismatch["seq"]})</span></span>'
        f'<details class="more"><summary>details</summary>'
        f"<p>{escape(str(mismatch.get('message', '')))}</p>"
        + (f"<ul>{fixes}</ul>" if fixes else "")
        + "</details>"
    )


def alarm_cell_html(alarm: dict | None, others: list[dict], mismatch: bool = False) -> str:
    """The fleet's alarm cell: the headline (the first unresolved fault,
    :func:`ajtwin.engine.views.headline_alarm`) and the print's other alarms beneath it.
    ``mismatch``: the newest print's alarms are the model–machine mismatch the status column
    already names (not a fault)."""
    if not alarm:
        text = "none (its alarms are the mismatch)" if mismatch else "none"
        return f'<span class="dim">{text}</span>'
    where = f"print #{alarm['seq']}, " if alarm.get("seq") else "live, "
    words = alarm.get("words") or alarm["description"]
    action = alarm.get("action")
    cell = (
        f'<span class="cause headline" title="{escape(str(alarm["description"]))}">'
        f"{escape(str(words))}</span><br>"
        + (f'<span class="action">{escape(str(action))}</span><br>' if action else "")
        + f'<span class="dim">{where}{alarm["detected_s"] / 60:.1f} min in'
        + (f" · {_when(alarm.get('ingested_at'))}" if alarm.get("ingested_at") else "")
        + "</span>"
    )
    if others:
        listed = "; ".join(
            f"{escape(str(a['cause']).replace('_', ' '))} at {a['detected_s'] / 60:.1f} min"
            for a in sorted(others, key=lambda a: a["detected_s"])
        )
        cell += f'<br><span class="dim others">also: {listed}</span>'
    return cell


def fleet_rows(machines: list[dict]) -> str:
    """The ``<tbody>`` rows of the fleet table."""
    if not machines:
        return (
            '<tr><td colspan="9" class="empty">No machines in this registry yet: '
            "<code>ajtwin machine add NAME</code>, then <code>ajtwin ingest</code>.</td></tr>"
        )
    rows = []
    for m in machines:
        name = escape(m["name"])
        status = m["status"]
        badge = f'<span class="status {status}">{escape(STATUS_TEXT.get(status, status))}</span>'
        mismatch = m.get("mismatch")
        if mismatch:  # the newest print's model–machine guard fired: one line, details folded
            badge += "<br>" + mismatch_html(mismatch)
        link = m.get("link")
        if link and link.get("text"):  # the live twin's machine link (ajtwin live --dashboard)
            badge += "<br>" + link_badge(link)
        last = m.get("last_print")
        if m.get("live"):
            now = "live" if m["live"].get("printing") else "live print ended"
            last_cell = f"{now}: {m['live']['time_s'] / 60:.1f} min"
        elif last:
            last_cell = (
                f"#{last['seq']} · {duration(last['duration_s'])}<br>"
                f'<span class="dim">{_when(last["ingested_at"])}</span>'
            )
        else:
            last_cell = '<span class="dim">no prints</span>'
        alarm_cell = alarm_cell_html(
            m.get("alarm"), m.get("other_alarms") or [], mismatch=bool(mismatch)
        )
        state_cells = []
        for s in m.get("states") or [None] * 4:
            if s is None:
                state_cells.append('<td class="num dim">—</td>')
                continue
            scale = s.get("scale", 1.0)
            band = "" if s.get("std") is None else f" ± {fmt(2 * s['std'] * scale)}"
            state_cells.append(
                f'<td class="num"><span class="val">{fmt(s["mean"] * scale, s["unit"])}</span>'
                f'<span class="dim">{band}</span><br>{sparkline(s.get("trend"))}</td>'
            )
        # what-if needs a registered machine with a print (its state and limits)
        whatif = f'<a href="/whatif/{machine_path(m["name"])}">what-if</a>' if last else ""
        care = []
        for key, label in (
            ("commissioned_at", "last commissioned"),
            ("last_maintenance_at", "last maintained"),
        ):
            if m.get(key):
                care.append(f'<span class="care">{label} {_when(str(m[key]))}</span>')
        care_cell = "<br>".join(care) if care else '<span class="dim">not recorded</span>'
        rows.append(
            f'<tr data-machine="{name}" data-status="{escape(status)}">'
            f'<td><a href="/machine/{machine_path(m["name"])}">{name}</a></td><td>{badge}</td>'
            f"<td>{last_cell}</td><td>{alarm_cell}</td>{''.join(state_cells)}"
            f"<td>{care_cell}</td><td>{whatif}</td></tr>"
        )
    return "\n".join(rows)


def fleet_page(machines: list[dict], store: str) -> str:
    """The fleet page: one row per machine (filled and refreshed by the page's script)."""
    head = "".join(
        f"<th>{s}<br><span class='dim'>now ± 2σ, last print</span></th>"
        for s in ("d_a [µm]", "φ_A [ppm by volume]", "ΔR_N [µm]", "V_l [mL]")
    )
    body = f"""
<h1>Fleet <span class="dim small">{len(machines)} machine(s) · {escape(store)}</span></h1>
<table id="fleet" class="grid">
<thead><tr><th>Machine</th><th>Status</th><th>Last print</th><th>Fault (the first unresolved;
others beneath)</th>
{head}<th>Commissioned / maintained</th><th></th></tr></thead>
<tbody id="fleet-rows">
{fleet_rows(machines)}
</tbody></table>
<p class="dim small">Status: <b>alarm</b> = the last print (or the live one) raised an alarm;
<b>printing</b> = live samples within the last 30 s (beneath: the state of the live
twin's machine link, e.g. <i>link lost — reconnecting</i>; the gap is missing data);
<b>mismatch</b> = the model–machine guard fired on the newest print: the model does not fit
the machine (what does not fit beneath; not a fault: commission the machine).
States are the twin's estimate at the end of the last print
(live: now); the line is their course over that print. φ_A, the aerosol volume fraction in the
carrier gas, is in parts per million by volume; its level is known only relative to the
generation model (to the prior of its commissioning) unless that commissioning pinned it (a
profilometer-calibrated CNN or the weighed vial): the machine page says which.</p>
"""
    return _page("Fleet", body, "fleet", plots=False)


def machine_page(name: str) -> str:
    """A machine's page (its plots are drawn from ``/api/machine/NAME``)."""
    n = escape(name)
    body = _template("machine.html").substitute(name=n, path=machine_path(name))
    return _page(name, body, "machine", name)


def whatif_page(name: str, limits: dict, inputs_now, last_seq: int | None) -> str:
    """The what-if form of a machine: inputs now, the machine's limits, the last print."""
    n = escape(name)
    lim = {k: v for k, v in (limits or {}).items()}

    def rng(key, unit):
        if key not in lim:
            return ""
        lo, hi = lim[key]
        return f"{lo:g}–{hi:g} {unit}"

    now = (
        ", ".join(
            f"{s} {v:.4g} {u}"
            for s, v, u in zip(("I_A", "Q_c", "Q_s"), inputs_now, ("mA", "sccm", "sccm"))
        )
        if inputs_now is not None
        else "—"
    )
    start = f"the end of print #{last_seq}" if last_seq else "— (no prints yet)"
    body = _template("whatif.html").substitute(
        name=n,
        path=machine_path(name),
        start=escape(start),
        now=escape(now),
        lim_current=escape(rng("atomizer_current_mA", "mA")),
        lim_carrier=escape(rng("carrier_flow_sccm", "sccm")),
        lim_sheath=escape(rng("sheath_flow_sccm", "sccm")),
    )
    return _page(f"What-if {name}", body, "whatif", name)


def message_page(title: str, message: str) -> str:
    """A page that says one thing (e.g. an unknown machine)."""
    body = f'<h1>{escape(title)}</h1><p class="error">{escape(message)}</p>'
    return _page(title, body, "message")
