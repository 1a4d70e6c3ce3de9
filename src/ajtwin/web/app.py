"""The dashboard's web application (FastAPI): pages, JSON API, websocket, access control.

Routes
------
``GET /``                            fleet page (server-rendered table)
``GET /machine/{name}``              machine page (plots drawn by plotly.js)
``GET /whatif/{name}``               what-if and advice forms
``GET /api/fleet``                   fleet summaries (JSON)
``GET /api/machine/{name}``          machine, print history, alarms, live buffer
``GET /api/machine/{name}/print/{seq}``   one print's series for the plots
``GET /api/machine/{name}/print/{seq}/part``   the part map of a stored print with a job
                                     (``?tolerance=45±3`` instead of the stored one)
``GET /api/machine/{name}/part/live``     the part map of the live print so far
``POST /api/machine/{name}/forecast``     what-if (same function as ``ajtwin forecast``)
``POST /api/machine/{name}/advise``       advice (same function as ``ajtwin advise``)
``WS  /ws``                          pushed events: live samples, committed prints
``GET /static/…``                    dashboard.js/.css and plotly.min.js from the plotly wheel

Access: with a ``token`` every request must carry it (``Authorization: Bearer T``, the
``ajtwin_token`` cookie, or ``?token=T`` once — the server then sets the cookie) or gets
401; the websocket is refused the same way (HTTP 403), and also when a browser opens it
from a page of another origin (``Origin`` not this server's: any site could otherwise
read the live stream of a dashboard served without a token). A request that is not a
GET/HEAD/OPTIONS (the what-if forecast and advice, which start minutes of work) is refused
with HTTP 403 when a browser made it from a page of another site (:func:`cross_site_origin`:
``Origin``, else ``Referer``, else ``Sec-Fetch-Site``). The websocket only pushes:
a page that sends a message is closed with code 1003; at most :data:`MAX_WEBSOCKETS` are
open at once (more: 403); events go out as strict JSON whatever a publisher put in them
(:func:`ajtwin.web.publisher.event_text`). Nothing in the application changes a machine
(forecasts and advice are computations; the registry is opened read-only in spirit: no
write is ever issued). Bad what-if input gets HTTP 422 with a sentence saying what is
wrong, never a server error; so does a yes/no field that is not a JSON boolean (the text
``"false"`` would otherwise count as true).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import math
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
from fastapi import FastAPI, Request, Response, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse
from starlette.middleware.trustedhost import TrustedHostMiddleware

from ajtwin.apps.detection.mismatch import MISMATCH_CAUSE
from ajtwin.apps.planning.advice import advise
from ajtwin.apps.planning.forecast import Change, forecast, input_schedule, parse_duration
from ajtwin.apps.quality.part_map import parse_tolerance
from ajtwin.engine.start import machine_open_faults
from ajtwin.engine.views import (
    KEY_STATES,
    NAMES,
    STATE_SCALE,
    STATE_UNITS,
    RegistryView,
    headline_alarm,
    json_list,
)
from ajtwin.store.registry import RegistryError
from ajtwin.web import pages
from ajtwin.web.publisher import LivePublisher, event_text
from ajtwin.web.watcher import RegistryWatcher

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
COOKIE = "ajtwin_token"
#: what-if horizon and settling-time bounds [s]
MAX_HORIZON_S = 4 * 3600.0
MAX_SETTLE_S = 1800.0
#: the output model's range for a target linewidth [µm] (apps.forecast.MODEL_RANGE)
TARGET_RANGE_UM = (1.0, 200.0)
LOOPBACK_HOSTS = ["127.0.0.1", "localhost", "::1", "[::1]"]


class InputError(ValueError):
    """A what-if value a person typed that cannot be used: HTTP 422 with this message."""


def plotly_js_path() -> Path:
    """plotly.min.js as shipped inside the ``plotly`` wheel (served, never fetched)."""
    import plotly

    path = Path(plotly.__file__).parent / "package_data" / "plotly.min.js"
    if not path.is_file():
        raise FileNotFoundError(f"plotly.min.js not found in the plotly package ({path})")
    return path


def _authorized(token: str | None, headers, cookies, query) -> bool:
    if not token:
        return True
    offered = []
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        offered.append(auth[7:].strip())
    offered += [cookies.get(COOKIE, ""), query.get("token", "")]
    return any(o and hmac.compare_digest(o.encode(), token.encode()) for o in offered)


# --------------------------------------------------------------------------- #
# What-if input validation (human messages)
# --------------------------------------------------------------------------- #
_SHORT = {"I_A": (0, "atomizer_current_mA", "mA"), "Q_c": (1, "carrier_flow_sccm", "sccm"),
          "Q_s": (2, "sheath_flow_sccm", "sccm")}  # fmt: skip


def _number(text, what: str) -> float:
    try:
        value = float(str(text).strip())
    except (TypeError, ValueError):
        raise InputError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{what}: {text!r} is not a finite number")
    return value


def _flag(body: dict, key: str, what: str) -> bool:
    """A yes/no field of a form: a JSON ``true``/``false`` (absent or null: false).

    Anything else is refused: Python's ``bool("false")`` is True, so a client that sent the
    text ``"false"`` (or 0, or "no") would silently get the opposite of what it asked for.
    """
    value = body.get(key)
    if value is None:
        return False
    if isinstance(value, bool):
        return value
    raise InputError(f"{what}: expected true or false (a JSON boolean), got {value!r}")


def _duration(text, what: str) -> float:

    try:
        return parse_duration(str(text))
    except ValueError:
        raise InputError(f"{what}: cannot read {text!r} (use e.g. 90s, 5min, 1.5h)") from None


def _within(value: float, key: str, limits: dict, label: str, unit: str) -> None:
    lo, hi = limits[key]
    if not lo <= value <= hi:
        raise InputError(
            f"{label} {value:g} {unit} is outside this machine's limits {lo:g}–{hi:g} {unit}"
        )


def parse_forecast_request(body: dict, limits: dict, u_now) -> tuple:
    """(inputs schedule (T, 3), changes, horizon s, options) from the what-if form.

    Raises InputError with a sentence naming the field when a value cannot be used.
    """

    if not isinstance(body, dict):
        raise InputError("the request must be a JSON object")
    horizon_s = _duration(body.get("horizon", "30min"), "horizon")
    if not 1.0 <= horizon_s <= MAX_HORIZON_S:
        raise InputError(f"horizon must be between 1 s and {MAX_HORIZON_S / 3600:g} h")
    base = np.asarray(u_now, dtype=float)
    if body.get("inputs_now") not in (None, ""):
        raw = body["inputs_now"]
        if not isinstance(raw, list) or len(raw) != 3:
            raise InputError("inputs now: give three values I_A [mA], Q_c [sccm], Q_s [sccm]")
        base = np.array([_number(v, f"inputs now ({s})") for v, s in zip(raw, _SHORT)])
        for (symbol, (_, key, unit)), value in zip(_SHORT.items(), base):
            _within(value, key, limits, f"inputs now: {symbol}", unit)
    changes = []
    raw_changes = body.get("changes") or []
    if not isinstance(raw_changes, list):
        raise InputError("changes must be a list of {input, value, at}")
    for row, item in enumerate(raw_changes, start=1):
        if not isinstance(item, dict):
            raise InputError(f"change {row}: expected input, value and time")
        symbol = str(item.get("input", "")).strip()
        if symbol not in _SHORT:
            raise InputError(f"change {row}: unknown input {symbol!r} (use I_A, Q_c or Q_s)")
        index, key, unit = _SHORT[symbol]
        value = _number(item.get("value"), f"change {row}: {symbol}")
        _within(value, key, limits, f"change {row}: {symbol}", unit)
        at_s = _duration(item.get("at", "0s"), f"change {row}: time")
        if at_s >= horizon_s:
            raise InputError(
                f"change {row}: at +{at_s:g} s is not before the end of the horizon "
                f"({horizon_s:g} s)"
            )
        changes.append(Change(at_s, index, value))
    try:
        schedule = input_schedule(base, changes, horizon_s)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    options = {
        "nominal_theta": _flag(body, "nominal_theta", "nominal θ"),
        "with_sensor_noise": _flag(body, "with_sensor_noise", "with sensor noise"),
    }
    return schedule, changes, horizon_s, options


def parse_advise_request(body: dict) -> dict:
    """The advice form's fields checked: target, overspray limit, settle time, θ choice (InputError
    naming the field)."""
    if not isinstance(body, dict):
        raise InputError("the request must be a JSON object")
    target = _number(body.get("target"), "target linewidth")
    lo, hi = TARGET_RANGE_UM
    if not lo <= target <= hi:
        raise InputError(
            f"target linewidth {target:g} µm is outside the output model's range {lo:g}–{hi:g} µm"
        )
    max_o = body.get("max_overspray")
    max_overspray = None
    if max_o not in (None, ""):
        max_overspray = _number(max_o, "max overspray")
        if max_overspray <= 0:
            raise InputError(f"max overspray must be > 0 µm, got {max_overspray:g}")
    settle_s = _duration(body.get("settle", "120s"), "settling time")
    if not 1.0 <= settle_s <= MAX_SETTLE_S:
        raise InputError(f"settling time must be between 1 s and {MAX_SETTLE_S / 60:g} min")
    return {
        "target": target,
        "max_overspray": max_overspray,
        "settle_s": int(round(settle_s)),
        "nominal_theta": _flag(body, "nominal_theta", "nominal θ"),
        "anyway": _flag(body, "anyway", "advise with an open fault"),
    }


# --------------------------------------------------------------------------- #
# The application
# --------------------------------------------------------------------------- #
def create_app(
    store,
    *,
    token: str | None = None,
    publisher: LivePublisher | None = None,
    poll_s: float = 0.5,
    loopback_only: bool = True,
    feeds: list | None = None,
) -> FastAPI:
    """The dashboard for the registry at ``store``.

    Parameters
    ----------
    store : path of an existing registry
    token : str, optional
        Required on every request when given (module docstring).
    publisher : LivePublisher, optional
        Live samples come through it (a live engine calls ``publish``); a new one if None.
    poll_s : float
        Registry watcher interval [s].
    loopback_only : bool
        Accept only Host headers of the loopback interface (against DNS rebinding when
        served on 127.0.0.1 without a token).
    feeds : list, optional
        Objects with ``start()``/``stop()`` (e.g. :class:`ajtwin.engine.replay.VirtualPrintFeed`)
        started with the server and stopped with it.
    """
    view = RegistryView(store)
    publisher = publisher or LivePublisher()
    watcher = RegistryWatcher(view, publisher, poll_s=poll_s)
    feeds = list(feeds or [])
    app = FastAPI(
        title="ajtwin dashboard",
        lifespan=_lifespan(view, watcher, feeds),
        docs_url=None,
        redoc_url=None,
    )
    app.state.view = view
    app.state.publisher = publisher
    app.state.watcher = watcher
    app.state.feeds = feeds
    _add_access_control(app, token, loopback_only)
    _add_static_routes(app)
    _add_fleet_routes(app, view, publisher)
    _add_machine_routes(app, view, publisher)
    _add_whatif_routes(app, view)
    _add_websocket(app, token, publisher)
    return app


def _lifespan(view, watcher, feeds):
    """The server's lifespan: the registry watcher and the feeds run while it serves."""

    @contextlib.asynccontextmanager
    async def lifespan(app):
        task = asyncio.create_task(watcher.run())
        for feed in feeds:
            feed.start()
        try:
            yield
        finally:
            for feed in feeds:
                feed.stop()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            watcher.close()
            view.close()

    return lifespan


def _add_access_control(app: FastAPI, token: str | None, loopback_only: bool) -> None:
    """The token on every request, loopback Host headers without one, errors as JSON/HTML."""
    if loopback_only and not token:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=LOOPBACK_HOSTS)

    @app.middleware("http")
    async def require_token(request: Request, call_next):
        if not _authorized(token, request.headers, request.cookies, request.query_params):
            return PlainTextResponse(
                "401: this dashboard needs its access token "
                "(open the address printed by `ajtwin dashboard`, which ends in ?token=…)",
                status_code=401,
                headers={"WWW-Authenticate": "Bearer"},
            )
        response = await call_next(request)
        if token and request.query_params.get("token"):
            response.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        return response

    @app.middleware("http")
    async def refuse_cross_site(request: Request, call_next):
        if request.method not in SAFE_METHODS:
            foreign = cross_site_origin(request.headers)
            if foreign is not None:
                return JSONResponse({"error": cross_site_refusal(foreign)}, status_code=403)
        return await call_next(request)

    @app.exception_handler(InputError)
    async def input_error(request: Request, exc: InputError):
        return JSONResponse({"error": str(exc)}, status_code=422)

    @app.exception_handler(RegistryError)
    async def registry_error(request: Request, exc: RegistryError):
        if request.url.path.startswith("/api/"):
            return JSONResponse({"error": str(exc)}, status_code=404)
        return HTMLResponse(pages.message_page("Not found", str(exc)), status_code=404)


#: request methods that change nothing and start no work; every other one (POST: a forecast,
#: advice) is served only to the dashboard's own pages and to clients that are no browser
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def _origin_of(url: str) -> str:
    """``scheme://host[:port]`` of a URL (lower case; "" when it has none)."""
    parts = urlsplit(url.strip())
    return f"{parts.scheme}://{parts.netloc}".lower() if parts.scheme and parts.netloc else ""


def cross_site_origin(headers) -> str | None:
    """The page of another site that made this request, or None (the dashboard's own page, or
    a client that is no browser: a script sends no ``Origin``, and is judged by the token).

    A browser names the page behind every POST in ``Origin`` (older ones at least in
    ``Referer``), and ``Sec-Fetch-Site`` says whether it was another site. Without this check
    any web page the operator opens could make their browser start forecasts and advice on
    a dashboard served on 127.0.0.1 without a token (a ``text/plain`` POST needs no CORS
    preflight). ``Origin: null`` (a sandboxed frame, a local file) is another site too.
    """
    host = headers.get("host", "").lower()
    own = {f"http://{host}", f"https://{host}"} if host else set()
    origins = headers.getlist("origin")
    for origin in origins:
        if origin.strip().lower() not in own:
            return origin
    if origins:
        return None
    referer = headers.get("referer")
    if referer and _origin_of(referer) not in own:
        return _origin_of(referer) or referer
    if headers.get("sec-fetch-site", "").lower() == "cross-site":
        return "another site (Sec-Fetch-Site: cross-site)"
    return None


def cross_site_refusal(origin: str) -> str:
    """The sentence a cross-site request gets with its HTTP 403."""
    return (
        f"refused: this request came from a page of another site ({origin!r}), not from the "
        "dashboard's own pages; open the dashboard itself to run a forecast or advice"
    )


def _add_static_routes(app: FastAPI) -> None:
    """plotly.js, the dashboard's script and style sheet, an empty favicon."""

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon():
        return Response(status_code=204)

    @app.get("/static/plotly.min.js", include_in_schema=False)
    def plotly_js():
        # the file changes only with the installed plotly version: let browsers keep it
        return FileResponse(
            plotly_js_path(),
            media_type="text/javascript",
            headers={"Cache-Control": "public, max-age=86400"},
        )

    @app.get("/static/{name}", include_in_schema=False)
    def static(name: str):
        files = {"dashboard.js": "text/javascript", "dashboard.css": "text/css"}
        if name not in files:
            return PlainTextResponse("not found", status_code=404)
        return FileResponse(
            STATIC / name, media_type=files[name], headers={"Cache-Control": "no-cache"}
        )


def fleet_summaries(view: RegistryView, publisher: LivePublisher) -> list[dict]:
    """One summary per machine (registered, or only seen live), live samples merged in."""
    machines = view.fleet()
    known = {m["name"] for m in machines}
    for name in publisher.machines():
        if name not in known:
            machines.append(
                {
                    "name": name,
                    "status": "idle",
                    "last_print": None,
                    "alarm": None,
                    "other_alarms": [],
                    "states": None,
                    "n_prints": 0,
                    "live_only": True,
                }  # fmt: skip
            )
    for m in machines:
        _merge_live(m, publisher)
    return sorted(machines, key=lambda m: m["name"])


def _add_fleet_routes(app: FastAPI, view: RegistryView, publisher: LivePublisher) -> None:
    """The fleet page, its rows (refreshed by the page) and ``/api/fleet``."""

    @app.get("/", response_class=HTMLResponse)
    def fleet_page():
        return pages.fleet_page(fleet_summaries(view, publisher), str(view.path))

    @app.get("/fragment/fleet-rows", response_class=HTMLResponse)
    def fleet_rows():
        return pages.fleet_rows(fleet_summaries(view, publisher))

    @app.get("/api/fleet")
    def api_fleet():
        return {"machines": fleet_summaries(view, publisher), "names": NAMES}


def _known(view: RegistryView, publisher: LivePublisher, name: str) -> bool:
    return name in {m["name"] for m in view.registry.machines()} or (name in publisher.machines())


def _add_machine_routes(app: FastAPI, view: RegistryView, publisher: LivePublisher) -> None:
    """A machine's page, ``/api/machine/NAME`` (history, live samples, link) and a print."""

    @app.get("/machine/{name}", response_class=HTMLResponse)
    def machine_page(name: str):
        if not _known(view, publisher, name):
            view.registry.machine(name)  # raises RegistryError with the known names
        return pages.machine_page(name)

    @app.get("/api/machine/{name}")
    def api_machine(name: str):
        registered = name in {m["name"] for m in view.registry.machines()}
        if registered:
            out = view.machine(name)
        elif name in publisher.machines():
            out = {"name": name, "prints": [], "alarms": [], "last": None, "names": NAMES,
                   "live_only": True}  # fmt: skip
        else:
            view.registry.machine(name)  # RegistryError → 404
        out["live"] = {
            "printing": publisher.is_printing(name),
            "samples": publisher.snapshot(name),
            "alarms": publisher.alarms(name),
        }
        out["link"] = publisher.link(name)
        out["status"] = _status(out, publisher)
        out["live_part"] = publisher.part_snapshot(name) is not None
        return out

    @app.get("/api/machine/{name}/print/{seq}")
    def api_print(name: str, seq: int):
        return view.print_series(name, seq)

    @app.get("/api/machine/{name}/print/{seq}/part")
    async def api_print_part(name: str, seq: int, tolerance: str | None = None):
        tol = None
        if tolerance not in (None, ""):
            try:
                tol = parse_tolerance(tolerance)
            except ValueError as exc:
                raise InputError(str(exc)) from None
        return await asyncio.to_thread(view.part_map, name, seq, tol)

    @app.get("/api/machine/{name}/part/live")
    def api_live_part(name: str):
        part = publisher.part_snapshot(name)
        if part is None:
            return JSONResponse({"error": f"no live part map of {name!r}"}, status_code=404)
        return part


async def json_body(request: Request):
    """A request's JSON body (InputError when it is not JSON or nested absurdly deep)."""
    try:
        return await request.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InputError("the form did not arrive as JSON; reload the page") from None
    except RecursionError:  # JSON nested thousands deep: no form sends that
        raise InputError("the request is nested too deeply to be a what-if form") from None


def forecast_response(view: RegistryView, name: str, body) -> dict:
    """The what-if form's forecast: outputs ± σ under the planned changes (≤ 900 points)."""
    twin, mean, cov, u_now, limits, seq = view.forecast_start(name)
    schedule, changes, horizon_s, options = parse_forecast_request(body, limits, u_now)
    if options["nominal_theta"]:
        twin.theta = np.zeros(5)
    fc = forecast(twin, mean, cov, schedule, include_measurement_noise=options["with_sensor_noise"])
    idx = np.unique(np.linspace(0, len(fc.time_s) - 1, min(len(fc.time_s), 900)).astype(int))
    return {
        "machine": name,
        "from_print": seq,
        "time_min": (fc.time_s[idx] / 60.0).tolist(),
        "inputs": fc.inputs[idx].tolist(),
        "outputs": fc.output_means[idx, :4].tolist(),
        "output_stds": fc.output_stds[idx, :4].tolist(),
        "output_names": list(NAMES["outputs"][:4]),
        "output_units": list(NAMES["output_units"][:4]),
        "changes": [
            {"at_s": c.time_s, "input": NAMES["inputs"][c.input_index], "value": c.value}
            for c in changes
        ],
        "theta": twin.theta.tolist(),
        "warnings": fc.warnings,
        "end": {
            n: [float(fc.output_means[-1, i]), float(fc.output_stds[-1, i])]
            for i, n in enumerate(NAMES["outputs"][:4])
        },
    }


def advice_response(view: RegistryView, name: str, body) -> dict:
    """The what-if form's advice: inputs that reach the target linewidth, and why (not)."""
    req = parse_advise_request(body)
    faulty_print, faults = machine_open_faults(view.registry, name)
    if faults and not req["anyway"]:
        # as `ajtwin advise`: advice now would steer the inputs around the fault
        raise InputError(
            f"not advising: print #{faulty_print} raised a fault no maintenance has closed "
            f"since: {faults[0]['sentence']}. Tick 'advise with an open fault' to advise all "
            "the same."
        )
    twin, mean, cov, u_now, limits, seq = view.forecast_start(name, req["nominal_theta"])
    try:
        advice = advise(
            twin,
            mean,
            cov,
            u_now,
            req["target"],
            max_overspray_um=req["max_overspray"],
            limits=limits,
            settle_s=req["settle_s"],
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
    rows = [
        {"name": n, "now": now, "advised": new, "std": std} for n, now, new, std in advice.rows()
    ]
    return {
        "machine": name,
        "from_print": seq,
        "rows": rows,
        "reachable": advice.reachable,
        "overspray_ok": advice.overspray_ok,
        "message": advice.message,
        "bounds": advice.bounds,
        "settle_s": advice.settle_s,
        "at_limits": advice.at_limits,
        "limit_note": advice.limit_note(),
        "open_fault": faults[0]["sentence"] if faults else None,
    }


def _add_whatif_routes(app: FastAPI, view: RegistryView) -> None:
    """The what-if page and its forecast and advice requests (run in a worker thread)."""

    @app.get("/whatif/{name}", response_class=HTMLResponse)
    def whatif_page(name: str):
        machine = view.registry.machine(name)
        last = view.registry.last_print(name)
        u_now = None
        if last is not None:
            _, _, _, u_now, _, _ = view.forecast_start(name)
        return pages.whatif_page(name, machine["limits"], u_now, last and last["seq"])

    @app.post("/api/machine/{name}/forecast")
    async def api_forecast(name: str, request: Request):
        body = await json_body(request)
        return await asyncio.to_thread(forecast_response, view, name, body)

    @app.post("/api/machine/{name}/advise")
    async def api_advise(name: str, request: Request):
        body = await json_body(request)
        return await asyncio.to_thread(advice_response, view, name, body)


def _add_websocket(app: FastAPI, token: str | None, publisher: LivePublisher) -> None:
    """``/ws``: live events pushed to the pages (authorised, same origin, at most
    :data:`MAX_WEBSOCKETS` at once)."""
    open_sockets: set = set()

    @app.websocket("/ws")
    async def ws(websocket: WebSocket):
        if not _authorized(
            token, websocket.headers, websocket.cookies, websocket.query_params
        ) or not _same_origin(websocket.headers):
            await websocket.close(code=1008)  # before accept: HTTP 403
            return
        if len(open_sockets) >= MAX_WEBSOCKETS:
            await websocket.close(code=1013)
            return
        machine = websocket.query_params.get("machine") or None
        await websocket.accept()
        sub = publisher.subscribe()
        open_sockets.add(sub)
        sender = asyncio.create_task(_send_events(websocket, sub, machine))
        try:
            await _read_until_closed(websocket)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            publisher.unsubscribe(sub)
            open_sockets.discard(sub)


#: open websockets at most (each holds a queue of up to 2,000 events); more are refused
MAX_WEBSOCKETS = 64
#: the close reason a page gets when it sends a message
SEND_ONLY = "this websocket only sends events; a page sends nothing"


def _same_origin(headers) -> bool:
    """Only the dashboard's own pages may open its websocket.

    A browser names the page that opens a websocket in ``Origin``, and websockets have no
    same-origin rule of their own: without this, a page of any site the operator visits
    could read the live stream of a dashboard served without a token on 127.0.0.1. A
    client that sends no ``Origin`` (a script) is judged by the token alone.
    """
    origins = headers.getlist("origin")
    if not origins:
        return True
    host = headers.get("host", "").lower()
    own = (f"http://{host}", f"https://{host}")
    return bool(host) and all(origin.lower() in own for origin in origins)


async def _read_until_closed(websocket: WebSocket) -> None:
    """Read the page's side until it leaves. Pages send nothing: a message is answered
    with close code 1003 and :data:`SEND_ONLY`. Reading all the time is also how a page
    that left without a close is noticed at once (uvicorn stops reading a connection
    whose messages the application does not take)."""
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        if message["type"] == "websocket.receive":
            with contextlib.suppress(RuntimeError):  # already closing
                await websocket.close(code=1003, reason=SEND_ONLY)


async def _send_events(websocket: WebSocket, sub, machine: str | None) -> None:
    """Push the hello, then every event (of ``machine`` only, when given) as strict JSON."""
    try:
        await websocket.send_text(event_text({"type": "hello"}))
        while True:
            event = await sub.get()
            if machine and event.get("machine") not in (None, machine):
                continue
            await websocket.send_text(event_text(event))
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass  # the page left or was closed: the reader ends the handler


def _merge_live(entry: dict, publisher: LivePublisher) -> None:
    """Overlay a machine's live state (printing, states now, live alarms) on its summary."""
    name = entry["name"]
    link = publisher.link(name)
    if link is not None:
        entry["link"] = link
    latest = publisher.latest(name)
    printing = publisher.is_printing(name)
    if latest is None:
        return
    # a registered machine shows its live state while printing; a live-only machine keeps
    # showing its last live state after the print ended (it has nothing else)
    if printing or entry.get("live_only"):
        entry["live"] = {"time_s": latest["time_s"], "printing": printing}
        if latest.get("states") is not None:
            samples = publisher.snapshot(name)
            step = max(1, len(samples) // 60)
            trend_t = [s["time_s"] for s in samples[::step] if s.get("states")]
            states = []
            for k in KEY_STATES:
                trend_v = [s["states"][k] for s in samples[::step] if s.get("states")]
                states.append(
                    {
                        "symbol": NAMES["states"][k],
                        "unit": STATE_UNITS[k],
                        "scale": STATE_SCALE[k],
                        "mean": latest["states"][k],
                        "std": (latest.get("state_stds") or [None] * 5)[k],
                        "trend": {"t": json_list(trend_t), "v": json_list(trend_v)},
                    }  # fmt: skip
                )
            entry["states"] = states
    alarms = publisher.alarms(name)
    if alarms:  # the live print's: its first unresolved fault, the rest beneath
        live = [{**a, "seq": None, "ingested_at": None} for a in alarms]
        entry["alarm"], entry["other_alarms"] = headline_alarm(live)
    entry["status"] = _status(entry, publisher)


def _status(entry: dict, publisher: LivePublisher) -> str:
    name = entry["name"]
    if publisher.alarms(name):  # the live print (running or the last one) raised an alarm
        return "alarm"
    if publisher.is_printing(name):
        return "printing"
    if entry.get("status") == "alarm":
        return "alarm"
    if entry.get("prints") is not None:  # machine detail: the fleet's rule (data.fleet)
        prints = entry["prints"]
        last_seq = prints[-1]["seq"] if prints else None
        if any(
            a.get("seq") == last_seq and a.get("cause") != MISMATCH_CAUSE
            for a in entry.get("alarms") or []
        ):
            return "alarm"  # a fault in the latest print
        return "mismatch" if entry.get("mismatch") else "idle"
    if entry.get("mismatch"):
        return "mismatch"
    return entry.get("status", "idle")
