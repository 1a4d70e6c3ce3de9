"""Fuzzing the wire surfaces with hypothesis (issue 14): the dashboard's HTTP API and the
live engine's OPC UA sample intake.

HTTP (:mod:`ajtwin.web.app`, in-process with fastapi's TestClient, no port): every route
that takes user input — machine names in paths (unicode, ``..``, control characters, very
long), print numbers, query parameters, the what-if forecast and advice JSON, the access
token in header, cookie and query. Property: 2xx with a well-formed body (strict JSON, no
NaN; or an HTML page), or 4xx with a human-readable message; never 5xx, never a
traceback in the body; a token-protected app never answers 2xx without the right token.

OPC UA (:func:`ajtwin.live.engine.clean_sample`, :func:`ajtwin.live.link.buffer_samples`,
:class:`ajtwin.live.engine.TwinStream`, no server): values as they arrive (NaN, ±inf,
huge/tiny, strings, bytes, None, lists, out-of-range, wrong buffer shapes, duplicate,
older and far-future time stamps). Property: each sample is accepted, treated as missing
or dropped, with a log line whenever it is not accepted as is; nothing raises; the
stream's time stays strictly increasing on the 1 s grid and its states and σ finite.

Profiles ``fuzz``/``fuzz-long`` as in ``tests/test_fuzz_inputs.py``; inputs that once
failed are replayed as explicit regression tests at the end of this module.
"""

from __future__ import annotations

import json
import logging
import math
import urllib.parse

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_fuzz_inputs import OUTCOMES, PROFILES, _report_outcomes  # noqa: F401  (autouse)
from test_web_data import hand_print

TOKEN = "fuzz-token-0123456789"


# --------------------------------------------------------------------------- #
# HTTP: the dashboard
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def web_store(tmp_path_factory):
    """One machine 'alpha' with one short hand-made print; 'idle' has none."""
    from ajtwin.store.registry import Registry

    path = tmp_path_factory.mktemp("fuzzweb") / "r.sqlite"
    reg = Registry(path)
    reg.add_machine("alpha")
    reg.add_machine("idle")
    hand_print(reg, "alpha", seq_before=None)
    reg.close()
    return path


@pytest.fixture(scope="module")
def clients(web_store):
    from fastapi.testclient import TestClient

    from ajtwin.web.app import create_app

    open_app = create_app(web_store)
    locked_app = create_app(web_store, token=TOKEN, loopback_only=False)
    base = "http://127.0.0.1"
    yield (
        TestClient(open_app, base_url=base, raise_server_exceptions=False),
        TestClient(locked_app, base_url=base, raise_server_exceptions=False),
    )
    open_app.state.view.close()
    locked_app.state.view.close()


def _no_nan(text):
    raise ValueError(f"non-standard JSON constant {text}")


def check_response(r, what: str) -> str:
    """The property for one answer; returns its outcome label for the counts."""
    body = r.text
    assert r.status_code < 500, f"{what}: HTTP {r.status_code}: {body[:500]}"
    assert "Traceback" not in body and 'File "' not in body, f"{what}: {body[:500]}"
    kind = r.headers.get("content-type", "")
    if 200 <= r.status_code < 300:
        if r.status_code == 204:
            return "204"
        if kind.startswith("application/json"):
            json.loads(body, parse_constant=_no_nan)  # strict JSON: no NaN/Infinity
        elif kind.startswith("text/html") and "/fragment/" not in what:
            assert "<html" in body.lower(), f"{what}: HTML answer without a page"
        return f"{r.status_code}"
    assert 400 <= r.status_code < 500, f"{what}: HTTP {r.status_code}"
    if kind.startswith("application/json"):
        doc = json.loads(body, parse_constant=_no_nan)
        message = doc.get("error") or doc.get("detail")
        if isinstance(message, list):  # FastAPI validation: [{"msg": ..., "loc": ...}]
            message = "; ".join(str(m.get("msg", "")) for m in message)
        assert isinstance(message, str) and len(message) > 3, f"{what}: {body[:300]}"
    else:
        assert len(body.strip()) > 3 and any(c.isalpha() for c in body), f"{what}: {body!r}"
    return f"{r.status_code}"


# machine names: the real one, path tricks, any unicode (no surrogates), control chars, long
names = st.one_of(
    st.sampled_from(["alpha", "idle", "nope", "..", ".", "../alpha", "alpha/..", "%2e%2e",
                     "al pha", "ALPHA", "alpha\x00", "\x00", "a" * 5000, "🖨️", "ａｌｐｈａ"]),
    st.text(max_size=40),
    st.text(alphabet=st.characters(max_codepoint=0x1F), max_size=10),
)  # fmt: skip
seqs = st.one_of(
    st.integers(-(2**70), 2**70).map(str),
    st.sampled_from(["1", "0", "-1", "1.5", "nan", "1e3", "", " 1", "0x1", "١"]),
    st.text(max_size=8),
)
# JSON-ish values a form field may carry
numbers_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(str),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e999", "", " ", "1,5", "0x10", "٣٧٥", "375",
                     "23", "50", "40", "12"]),
)  # fmt: skip
leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**30), 10**30),
    st.floats(allow_nan=False, allow_infinity=False),
    numbers_text,
    st.text(max_size=12),
)
any_json = st.recursive(
    leaf,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=8,
)
# durations: a few valid ones (each new horizon length compiles the forecast scan once)
durations = st.one_of(
    st.sampled_from(["30s", "1min", "90s", "+45", "0s", "0.5s", "-5min", "5h", "100000h",
                     "1e3s", "nan", "inf", "", "1 min", "30 sec", "s", "min"]),
    st.text(max_size=8),
    any_json,
)  # fmt: skip
change = st.fixed_dictionaries(
    {},
    optional={
        "input": st.one_of(st.sampled_from(["I_A", "Q_c", "Q_s", " Q_s ", "q_s", "P_c"]), any_json),
        "value": st.one_of(numbers_text, any_json),
        "at": st.one_of(st.sampled_from(["0s", "10s", "20s", "29s"]), durations),
    },
)
forecast_bodies = st.one_of(
    st.fixed_dictionaries(
        {},
        optional={
            "horizon": st.one_of(st.sampled_from(["30s", "1min", "90s"]), durations),
            "inputs_now": st.one_of(
                st.lists(numbers_text, min_size=0, max_size=4),
                st.just(["375", "23", "50"]),
                any_json,
            ),
            "changes": st.one_of(st.lists(change, max_size=3), any_json),
            "nominal_theta": any_json,
            "with_sensor_noise": any_json,
        },
    ),
    any_json,
)
advise_bodies = st.one_of(
    st.fixed_dictionaries(  # mostly usable: the advice itself gets exercised
        {"target": st.sampled_from(["40", "60", "1", "200", " 80 "])},
        optional={
            "max_overspray": st.sampled_from(["", "5", "0.1", "1e6"]),
            "settle": st.sampled_from(["120s", "60s"]),
            "nominal_theta": st.booleans(),
        },
    ),  # fmt: skip
    st.fixed_dictionaries(
        {},
        optional={
            "target": st.one_of(numbers_text, any_json),
            "max_overspray": st.one_of(numbers_text, any_json),
            "settle": st.one_of(st.sampled_from(["120s", "60s", "2min"]), durations),
            "nominal_theta": any_json,
        },
    ),
    any_json,
)
raw_bodies = st.one_of(
    st.binary(max_size=40),
    st.sampled_from([b"", b"NaN", b"[", b"{", b'{"target": 1e999}', b"\xff\xfe{}",
                     b'"x"', b"[" * 20_000 + b"]" * 20_000, b"{\"a\":" * 20_000]),
)  # fmt: skip


def q(name: str) -> str:
    return urllib.parse.quote(name, safe="")


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_http_paths_and_queries(profile, clients):
    client, _ = clients

    @settings(settings.get_profile(profile))
    @given(
        name=names,
        seq=seqs,
        route=st.sampled_from(["machine", "api", "print", "whatif", "static", "fleet"]),
        query=st.dictionaries(st.text(max_size=8), st.text(max_size=20), max_size=3),
    )
    def run(name, seq, route, query):
        path = {
            "machine": f"/machine/{q(name)}",
            "api": f"/api/machine/{q(name)}",
            "print": f"/api/machine/{q(name)}/print/{q(seq)}",
            "whatif": f"/whatif/{q(name)}",
            "static": f"/static/{q(name)}",
            "fleet": "/api/fleet",
        }[route]
        r = client.get(path, params=query)
        OUTCOMES[f"{route} {check_response(r, f'GET {path!r}')}"] += 1
        if route in ("api", "print") and name not in ("alpha", "idle"):
            assert r.status_code >= 400  # an unknown machine is never answered as known

    run()


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_http_forecast(profile, clients):
    client, _ = clients

    @settings(settings.get_profile(profile))
    @given(
        name=st.one_of(st.just("alpha"), names), body=forecast_bodies, raw=st.none() | raw_bodies
    )
    def run(name, body, raw):
        path = f"/api/machine/{q(name)}/forecast"
        if raw is None:
            r = client.post(path, json=body)
        else:
            r = client.post(path, content=raw, headers={"content-type": "application/json"})
        outcome = check_response(r, f"POST {path} {body if raw is None else raw[:80]!r}")
        if r.status_code == 200:
            doc = r.json()
            assert doc["machine"] == name == "alpha" and len(doc["time_min"]) >= 1
            assert len(doc["outputs"]) == len(doc["time_min"]) == len(doc["inputs"])
            assert all(math.isfinite(v) for row in doc["output_stds"] for v in row if v is not None)
        OUTCOMES[f"forecast {outcome}"] += 1

    run()


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_http_advise(profile, clients):
    client, _ = clients

    @settings(settings.get_profile(profile))
    @given(name=st.one_of(st.just("alpha"), names), body=advise_bodies, raw=st.none() | raw_bodies)
    def run(name, body, raw):
        path = f"/api/machine/{q(name)}/advise"
        if raw is None:
            r = client.post(path, json=body)
        else:
            r = client.post(path, content=raw, headers={"content-type": "application/json"})
        outcome = check_response(r, f"POST {path} {body if raw is None else raw[:80]!r}")
        if r.status_code == 200:
            doc = r.json()
            assert doc["machine"] == "alpha" and {row["name"] for row in doc["rows"]}
        OUTCOMES[f"advise {outcome}"] += 1

    run()


def _offers(token_like):
    """Header / cookie / query token candidates near the real token."""
    return st.one_of(
        st.none(),
        st.just(TOKEN),
        st.sampled_from(["", " ", TOKEN[:-1], TOKEN + "x", TOKEN.upper(), " " + TOKEN,
                         TOKEN + " ", "Bearer", "null", TOKEN[1:]]),
        token_like,
    )  # fmt: skip


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_http_token(profile, clients):
    _, client = clients
    ascii_text = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=30)

    @settings(settings.get_profile(profile))
    @given(
        header=_offers(ascii_text),
        scheme=st.sampled_from(["Bearer ", "bearer ", "BEARER  ", "Basic ", "", "Token "]),
        cookie=_offers(ascii_text.filter(lambda s: ";" not in s and '"' not in s)),
        query=_offers(st.text(max_size=30)),
        path=st.sampled_from(["/", "/api/fleet", "/api/machine/alpha", "/machine/alpha",
                              "/whatif/alpha", "/static/dashboard.js", "/favicon.ico",
                              "/api/machine/alpha/print/1", "/fragment/fleet-rows"]),
        method=st.sampled_from(["GET", "POST"]),
    )  # fmt: skip
    def run(header, scheme, cookie, query, path, method):
        headers = {}
        if header is not None:
            headers["authorization"] = scheme + header
        client.cookies.clear()
        if cookie is not None:
            client.cookies.set("ajtwin_token", cookie)
        params = {} if query is None else {"token": query}
        if method == "POST":
            path = "/api/machine/alpha/advise"
            r = client.post(path, headers=headers, params=params, json={"target": "40"})
        else:
            r = client.get(path, headers=headers, params=params)
        client.cookies.clear()
        bearer = (
            header.strip()
            if header is not None and (scheme + header).lower().startswith("bearer ")
            else None
        )
        # a cookie's surrounding blanks are not part of its value (RFC 6265 parsing)
        allowed = TOKEN in (bearer, cookie and cookie.strip(), query)
        outcome = check_response(r, f"{method} {path} auth={headers} cookie={cookie!r} q={query!r}")
        if not allowed:
            assert r.status_code == 401, (headers, cookie, query, r.status_code)
            OUTCOMES["token refused"] += 1
        else:
            assert r.status_code != 401
            OUTCOMES[f"token accepted {outcome}"] += 1

    run()
