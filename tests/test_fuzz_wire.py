"""Fuzzing the wire surfaces with hypothesis: the dashboard's HTTP API and the
live engine's OPC UA sample intake.

HTTP (:mod:`ajtwin.web.app`, in-process with fastapi's TestClient, no port): every route
that takes user input — machine names in paths (unicode, ``..``, control characters, very
long), print numbers, query parameters, the what-if forecast and advice JSON, the access
token in header, cookie and query. Property: 2xx with a well-formed body (strict JSON, no
NaN; or an HTML page), or 4xx with a human-readable message; never 5xx, never a
traceback in the body; a token-protected app never answers 2xx without the right token.

OPC UA (:func:`ajtwin.estimation.samples.clean_sample`, :func:`ajtwin.live.link.buffer_samples`,
:class:`ajtwin.engine.stream.TwinStream`, no server): values as they arrive (NaN, ±inf,
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
# the OPC UA surface has three fuzzers: 3,400 each in the slow run (10,200 in all; the HTTP
# surface's four run test_fuzz_inputs' 2,500 each)
settings.register_profile(
    "fuzz-long-wire", parent=settings.get_profile("fuzz-long"), max_examples=3400
)
WIRE_PROFILES = [
    pytest.param("fuzz", id="fuzz"),
    pytest.param("fuzz-long-wire", id="fuzz-long", marks=pytest.mark.slow),
]
# a stream-intake input steps the filter over every second of its gaps (up to 50 s each,
# ~360 steps an input): the default suite takes 20 of them, the slow run its 3,400
settings.register_profile("fuzz-stream", parent=settings.get_profile("fuzz"), max_examples=20)
STREAM_PROFILES = [
    pytest.param("fuzz-stream", id="fuzz"),
    pytest.param("fuzz-long-wire", id="fuzz-long", marks=pytest.mark.slow),
]


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


# --------------------------------------------------------------------------- #
# OPC UA wire data: the live engine's sample intake
# --------------------------------------------------------------------------- #
NOMINAL_U = [375.0, 23.0, 50.0]  # mA, sccm, sccm
NOMINAL_Y = [75.0, 8.0, 5800.0, 5750.0, 1.5e-8]  # µm, µm, Pa, Pa, mL/s

# one number as a Variant may carry it (or a client may mangle it)
wire_number = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-1e-300, max_value=1e-300),
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 5e-324, 0.0,
                     -0.0, 375.0, 23.0, 50.0, 0.375, 1e6]),
    st.integers(-(10**400), 10**400),
)  # fmt: skip
wire_junk = st.one_of(
    st.none(), st.text(max_size=6), st.binary(max_size=6), st.booleans(), st.complex_numbers(),
    st.sampled_from(["375", "nan", "", b"\x00", [], {}, [[1.0]], object()]),
)  # fmt: skip
wire_value = st.one_of(wire_number, wire_junk, st.lists(wire_number, max_size=4))


def _vector(nominal):
    """The nominal vector with some entries replaced, or the whole of it replaced."""
    n = len(nominal)
    return st.one_of(
        st.lists(st.tuples(st.integers(0, n - 1), wire_value), max_size=3).map(
            lambda subs: _substitute(nominal, subs)
        ),
        wire_value,
        st.lists(wire_number, min_size=n - 1, max_size=n + 1),
    )


def _mostly(nominal, share=7):
    """The nominal vector in ``share`` of 10 draws, else a fuzzed one (a filter has to run)."""
    return st.integers(0, 9).flatmap(lambda i: st.just(nominal) if i < share else _vector(nominal))


def _substitute(nominal, subs):
    out = list(nominal)
    for i, v in subs:
        out[i] = v
    return out


def _as_float_vector(value, n):
    """What the intake should see, computed independently (None: not n numbers)."""
    try:
        flat = [value] if not isinstance(value, (list, tuple)) else list(value)
        if len(flat) != n or any(isinstance(v, (str, bytes, complex, list, dict)) for v in flat):
            return None
        if any(v is None or not isinstance(v, (int, float)) for v in flat):
            return None
        return np.array([float(v) for v in flat])
    except OverflowError:
        return None


def check_clean(sample, problems, time_s, u_in, y_in):
    """The contract of clean_sample for one wire sample (independent of its code)."""
    from ajtwin.io.records import OUTPUT_COLUMNS, PLAUSIBLE_RANGES
    from ajtwin.model.names import INPUT_NAMES
    from ajtwin.model.system import INPUT_LIMITS

    assert all(isinstance(p, str) and len(p) > 10 for p in problems)
    if sample is None:
        assert problems, "a sample dropped without a log line"
        return "dropped"
    assert math.isfinite(sample.time_s) and abs(sample.time_s) <= 1e12
    u, y = np.asarray(sample.inputs, float), np.asarray(sample.outputs, float)
    assert u.shape == (3,) and y.shape == (5,)
    assert not np.isinf(y).any()
    if np.isnan(u).all():
        assert np.isnan(y).all() and problems, "missing without a log line"
        return "missing"
    for value, name in zip(u, INPUT_NAMES):
        low, high = INPUT_LIMITS[name]
        assert low < value <= high, (name, value)
    for value, column in zip(y, OUTPUT_COLUMNS):
        low, high = PLAUSIBLE_RANGES.get(column, (-np.inf, np.inf))[:2]
        assert np.isnan(value) or low <= value <= high, (column, value)
    # accepted: every input as sent; an output differs from what was sent only with a line
    expected_u, expected_y = _as_float_vector(u_in, 3), _as_float_vector(y_in, 5)
    if expected_u is not None:
        np.testing.assert_array_equal(u, expected_u)
    if expected_y is not None:
        changed = ~((y == expected_y) | (np.isnan(y) & np.isnan(expected_y)))
        assert not changed.any() or problems
        assert np.isnan(expected_y[changed]).sum() == 0  # only bad values become NaN
        return "accepted, outputs missing" if changed.any() else "accepted"
    return "accepted"


@pytest.mark.parametrize("profile", WIRE_PROFILES)
def test_fuzz_clean_sample(profile):
    from ajtwin.estimation.samples import clean_sample

    @settings(settings.get_profile(profile))
    @given(
        time_s=st.one_of(st.floats(-10, 1e6), wire_number, wire_junk),
        u=_mostly(NOMINAL_U, 3),
        y=_mostly(NOMINAL_Y, 3),
    )
    def run(time_s, u, y):
        sample, problems = clean_sample(time_s, u, y, where="aj1")
        OUTCOMES[check_clean(sample, problems, time_s, u, y)] += 1

    run()


@pytest.mark.parametrize("profile", WIRE_PROFILES)
def test_fuzz_sample_buffer(profile):
    """Link.SampleBuffer values → samples: the pure conversion the OPC UA link uses."""
    from ajtwin.estimation.samples import clean_sample
    from ajtwin.live.link import buffer_samples
    from ajtwin.live.opcua import SAMPLE_WIDTH

    # a Variant array of Doubles: any float in any cell, mostly the nominal value
    cells = [st.one_of(st.just(v), st.just(v), st.floats()) for v in NOMINAL_U + NOMINAL_Y]
    row = st.tuples(st.one_of(st.integers(-3, 40).map(float), st.floats()), *cells).map(list)

    @settings(settings.get_profile(profile))
    @given(
        rows=st.lists(row, max_size=8),
        shape=st.sampled_from(["rows", "flat", "junk"]),
        junk=wire_value,
        last=st.sampled_from([-np.inf, 0.0, 5.0, 1e9]),
    )
    def run(rows, shape, junk, last):
        value = {"rows": rows, "flat": [v for r in rows for v in r], "junk": junk}[shape]
        samples, new_last, problems = buffer_samples("aj1", value, last)
        times = [s.time_s for s in samples]
        assert all(b > a for a, b in zip([last, *times], times)), (last, times)
        assert new_last == (times[-1] if times else last)
        try:
            table = np.asarray(value, dtype=float).reshape(-1, SAMPLE_WIDTH)
        except (TypeError, ValueError, OverflowError):
            assert not samples and problems
            OUTCOMES["buffer refused"] += 1
            return
        # independent replay: rows newer than the running last, each through clean_sample
        expected, running, lines = [], last, 0
        for r in table:
            if np.isnan(r).all():  # an unfilled slot of the buffer: no sample, no line
                continue
            if not np.isfinite(r[0]):
                lines += 1
                continue
            if r[0] <= running:
                continue
            s, p = clean_sample(r[0], r[1:4], r[4:])
            lines += len(p)
            if s is not None:
                expected.append(s)
                running = s.time_s
        assert len(problems) == lines
        assert times == [s.time_s for s in expected]
        for got, want in zip(samples, expected):
            np.testing.assert_array_equal(got.inputs, want.inputs)
            np.testing.assert_array_equal(got.outputs, want.outputs)
        OUTCOMES[f"buffer: {len(samples)} samples, {len(problems)} log lines"[:40]] += 1

    run()


class _Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records = []

    def emit(self, record):
        self.records.append(record.getMessage())


@pytest.fixture(scope="module")
def fitted_start():
    """A start state fitted from ten nominal samples (the stream's own initial fit)."""
    from ajtwin.engine.stream import TwinStream
    from ajtwin.estimation.samples import Sample

    stream = TwinStream.new("fit", twin_overrides={"em": False}, asynchronous=False)
    for k in range(stream.config.initial_samples):
        stream.feed(Sample(float(k), np.array(NOMINAL_U), np.array(NOMINAL_Y)))
    assert stream.carry is not None
    return stream.start_mean, stream.start_cov


@pytest.mark.parametrize("profile", STREAM_PROFILES)
def test_fuzz_stream_intake(profile, fitted_start):
    """Wire samples → clean_sample → TwinStream.feed, in any time order."""
    from ajtwin.engine.stream import TwinStream
    from ajtwin.estimation.samples import MAX_GAP_S, clean_sample

    steps = st.one_of(
        st.just(1.0),  # mostly the next second: the filter has to run
        st.just(1.0),
        st.just(1.0),
        st.just(1.0),
        st.just(1.0),
        st.just(1.0),
        st.sampled_from([0.0, -1.0, -30.0, 0.4, 0.6, 1.4, 2.0, 5.0, float(MAX_GAP_S) + 1.0,
                         1e7, 1e12, 1e300, -1e300, float("nan"), float("inf")]),
        st.floats(-50, 50),
    )  # fmt: skip
    event = st.tuples(
        steps,
        _mostly(NOMINAL_U),
        _mostly(NOMINAL_Y),
    )

    @settings(settings.get_profile(profile))
    @given(events=st.lists(event, min_size=1, max_size=25), t0=st.sampled_from([0.0, 1.7e9]))
    def run(events, t0):
        lines = _Lines()
        logger = logging.getLogger("ajtwin.live")
        old_level = logger.level
        logger.addHandler(lines)
        logger.setLevel(logging.DEBUG)
        try:
            stream = TwinStream(
                "aj1",
                _twin(),
                start=fitted_start,
                asynchronous=False,
            )
            t = t0
            for dt, u, y in events:
                sent = t + dt if math.isfinite(dt) else dt
                if math.isfinite(sent) and abs(sent) < 1e13:
                    t = sent  # the clock goes on from a readable time stamp
                sample, problems = clean_sample(sent, u, y, where="aj1")
                if sample is None:
                    assert problems
                    OUTCOMES["dropped at intake"] += 1
                    continue
                counts = dict(stream.dropped)
                before = (stream.n_received, sum(stream.dropped.values()), len(lines.records))
                stream.feed(sample)
                after = (stream.n_received, sum(stream.dropped.values()), len(lines.records))
                why = [k for k in counts if stream.dropped[k] > counts[k]]
                if after[0] > before[0]:
                    OUTCOMES["missing" if problems and np.isnan(sample.outputs).all()
                             else "taken"] += 1  # fmt: skip
                else:  # not taken: counted as dropped, with a log line
                    assert after[1] > before[1] and after[2] > before[2], (t, sample)
                    OUTCOMES[f"dropped by the stream: {why[0]}"] += 1
            stream.finish()
        finally:
            logger.removeHandler(lines)
            logger.setLevel(old_level)
        arrays = stream.arrays()
        time_s = arrays["time_s"]
        if len(time_s) > 1:
            np.testing.assert_allclose(np.diff(time_s), 1.0)  # the 1 s grid, never reordered
        assert np.isfinite(arrays["means"]).all()
        cov = arrays["covariances"]  # a stream keeps its last steps
        assert np.isfinite(cov).all()
        if len(cov):
            assert (np.diagonal(cov, axis1=1, axis2=2) >= 0).all()  # σ real

    run()


_TWIN = {}


def _twin():
    """One default twin without EM (25-sample sequences never reach an EM window anyway)."""
    from ajtwin.estimation import Twin

    if "twin" not in _TWIN:
        _TWIN["twin"] = Twin.default(em=False)
    return _TWIN["twin"]


# --------------------------------------------------------------------------- #
# Inputs that once failed (found by the fuzzers above), kept as regression cases
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("seq", [str(2**63), str(-(2**63) - 1), str(2**70)])
def test_print_number_beyond_sqlite_integers_is_a_404(clients, seq):
    """Found by the fuzz-long run (once in several: the generator reaches 2⁶³ with
    name 'alpha' and the print route rarely): OverflowError in the SQLite binding, HTTP 500."""
    client, _ = clients
    r = client.get(f"/api/machine/alpha/print/{seq}")
    assert r.status_code == 404 and "has no print" in check_response(r, seq) + r.text


def test_deeply_nested_json_is_a_422(clients):
    """``[[[[…`` 20,000 deep → RecursionError in the JSON parser → HTTP 500 (was)."""
    client, _ = clients
    for path in ("/api/machine/alpha/forecast", "/api/machine/alpha/advise"):
        r = client.post(path, content=b"[" * 20_000 + b"]" * 20_000)
        assert r.status_code == 422 and "nested too deeply" in r.json()["error"]


@pytest.mark.parametrize(
    "time_s, u, y",
    [
        (10**400, NOMINAL_U, NOMINAL_Y),  # was OverflowError out of clean_sample
        (1.0, [10**400, 23.0, 50.0], NOMINAL_Y),  # same, from the inputs
        (1.0, NOMINAL_U, [75.0, 8.0, 5800.0, 5750.0, "x"]),  # was None though "treated as missing"
    ],
)
def test_wire_values_that_raised_or_were_dropped(time_s, u, y):
    from ajtwin.estimation.samples import clean_sample

    sample, problems = clean_sample(time_s, u, y, where="aj1")
    assert problems and problems[0].startswith("aj1: ")
    if time_s == 1.0:  # a readable time: the step is kept, as missing data
        assert sample.time_s == 1.0 and np.isnan(sample.inputs).all()
        assert np.isnan(sample.outputs).all() and "treated as missing" in problems[0]
    else:
        assert sample is None and "dropped" in problems[0]


def test_far_future_time_stamp_is_dropped_not_filled(fitted_start, caplog, monkeypatch):
    """t = 1e7 s after t = 0 was filled with 10 million missing steps (minutes, memory);
    t = 1e300 was accepted as a time."""
    from ajtwin.engine.stream import TwinStream
    from ajtwin.estimation import online
    from ajtwin.estimation.samples import Sample, clean_sample

    monkeypatch.setattr(online, "MAX_GAP_S", 5)  # the real limit (hours) works the same
    MAX_GAP_S = 5
    stream = TwinStream("aj1", _twin(), start=fitted_start, asynchronous=False)
    u, y = np.array(NOMINAL_U), np.array(NOMINAL_Y)
    stream.feed(Sample(0.0, u, y))
    with caplog.at_level(logging.WARNING, logger="ajtwin.live"):
        stream.feed(Sample(1e7, u, y))
    assert stream.dropped["far_future"] == 1 and stream.n_received == 1
    assert "ahead of the last step" in caplog.text
    stream.feed(Sample(1.0, u, y))  # the clock goes on: taken
    stream.feed(Sample(2.0 + MAX_GAP_S, u, y))  # an outage of MAX_GAP_S s: still filled
    assert stream.n_received == 3 + MAX_GAP_S and stream.missing_inserted == MAX_GAP_S
    stream.feed(Sample(4.0 + 2 * MAX_GAP_S, u, y))  # one second more: dropped
    assert stream.dropped["far_future"] == 2
    assert clean_sample(1e300, u, y)[0] is None


def test_buffer_padding_rows_are_skipped_silently():
    """A buffer not yet full is padded with all-NaN rows (printer_server): `ajtwin demo
    --live` printed one "row with time nan; dropped" line per padding row and sample."""
    from ajtwin.live.link import buffer_samples
    from ajtwin.live.opcua import SAMPLE_WIDTH

    rows = np.full((4, SAMPLE_WIDTH), np.nan)
    rows[3] = [7.0, *NOMINAL_U, *NOMINAL_Y]
    samples, last, problems = buffer_samples("aj1", rows, 6.0)
    assert [s.time_s for s in samples] == [7.0] and last == 7.0 and problems == []
    rows[0, 1] = 375.0  # a row with values but no time is not padding: it is logged
    assert len(buffer_samples("aj1", rows, 6.0)[2]) == 1
