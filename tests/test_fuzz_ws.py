"""Fuzzing the dashboard's websocket with hypothesis, as tests/test_fuzz_wire.py
fuzzes its HTTP API and the OPC UA intake.

Two surfaces:

* **The socket** (``WS /ws`` of ``ajtwin dashboard``, a real server in a child process on
  127.0.0.1 and a free port, with a token and a virtual live print so that events flow
  while the client misbehaves; stopped by its PID). Raw TCP: an opening handshake with
  fuzzed path, query (machine, token), headers (Upgrade, Connection, key, version, Origin,
  Authorization, Cookie, subprotocols, extensions), then a sequence of raw frames (every
  opcode, fragments, reserved bits, unmasked, control frames too long, close codes of any
  value, invalid UTF-8, lengths that lie, messages over the size limit). Property: the
  handshake is answered with 101 or a 4xx, never 5xx, and 101 only with the right token
  and from the dashboard's own origin; after the frames the server either still answers
  a ping (the connection alive) or has sent a close frame with a defined code (a protocol
  error 1002, unsupported data 1003, invalid UTF-8 1007, too big 1009, or the client's
  own close) — never a hang, a 1011 or a dropped connection without a close; every text
  frame it sends is strict JSON; the server process never dies and logs no traceback.
* **The events it pushes** (:class:`ajtwin.web.publisher.LivePublisher`, in-process):
  samples, engine messages, link states and announcements with any content (NaN, ±inf,
  non-string keys, bytes, NumPy values, tuples, sets, objects, deep nesting). Property:
  ``publish`` refuses with a ``ValueError`` naming what is wrong, or every page receives
  the event as strict JSON (:func:`ajtwin.web.app.event_text`).

Profiles ``fuzz`` (60 each, default suite) and ``fuzz-long`` (3,400 each, 10,200 in all,
``-m slow``). Inputs that once failed are replayed at the end.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import socket
import struct
import time
import urllib.parse

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_fuzz_inputs import OUTCOMES, _report_outcomes  # noqa: F401  (autouse)
from test_web_data import hand_print

TOKEN = "ws-fuzz-token-0123456789"
# three fuzzers: 3,400 each in the slow run (10,200 in all), 60 each in the default suite
settings.register_profile(
    "fuzz-long-ws", parent=settings.get_profile("fuzz-long"), max_examples=3400
)
WS_PROFILES = [
    pytest.param("fuzz", id="fuzz"),
    pytest.param("fuzz-long-ws", id="fuzz-long", marks=pytest.mark.slow),
]
GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
IO_TIMEOUT_S = 10.0  # every read from the server is bounded by this (2 loaded cores)
#: close codes the server may send after the fuzzed frames (plus the client's own close)
SERVER_CLOSE_CODES = {1000, 1001, 1002, 1003, 1007, 1008, 1009}


# --------------------------------------------------------------------------- #
# the server
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from ajtwin.store.registry import Registry
    from ajtwin.web.server import DashboardProcess

    folder = tmp_path_factory.mktemp("fuzzws")
    reg = Registry(folder / "r.sqlite")
    reg.add_machine("alpha")
    hand_print(reg, "alpha", seq_before=None)
    reg.close()
    # a virtual live print: a sample a second for an hour (the slow run lasts ~40 min)
    dash = DashboardProcess(
        folder / "r.sqlite",
        token=TOKEN,
        extra_args=["--virtual-print", "exp1", "--virtual-minutes", "60",
                    "--virtual-rate", "1", "--virtual-machine", "vm1"],
        log_path=folder / "server.log",
        startup_timeout_s=300,
    )  # fmt: skip
    dash.start()
    try:
        yield dash
    finally:
        dash.stop()
    text = (folder / "server.log").read_text(errors="replace")
    assert "Traceback" not in text and "Exception in ASGI" not in text, text[-3000:]


def _check_server(server):
    assert server.proc.poll() is None, server.log_path.read_text(errors="replace")[-3000:]


class Conn:
    """A raw TCP connection to the server with bounded reads."""

    def __init__(self, server):
        self.sock = socket.create_connection((server.host, server.port), timeout=IO_TIMEOUT_S)
        self.buf = b""

    def close(self):
        self.sock.close()

    def send(self, data: bytes) -> bool:
        try:
            self.sock.sendall(data)
            return True
        except OSError:  # the server closed first (after a close frame or a 4xx)
            return False

    def _more(self, deadline) -> bool:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the server did not answer in time")
        self.sock.settimeout(left)
        try:
            chunk = self.sock.recv(65536)
        except ConnectionResetError:
            return False
        except TimeoutError:
            raise TimeoutError("the server did not answer in time") from None
        if not chunk:
            return False
        self.buf += chunk
        return True

    def response(self, deadline) -> tuple[int, dict, bytes]:
        """(status, headers, body) of the HTTP answer to the handshake."""
        while b"\r\n\r\n" not in self.buf:
            if not self._more(deadline):
                raise AssertionError(f"connection closed before a full answer: {self.buf!r}")
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {}
        for line in lines[1:]:
            k, _, v = line.partition(":")
            headers[k.strip().lower()] = v.strip()
        body = b""
        if status != 101:
            n = int(headers.get("content-length", "0"))
            while len(self.buf) < n and self._more(deadline):
                pass
            body, self.buf = self.buf[:n], self.buf[n:]
        return status, headers, body

    def frame(self, deadline):
        """(fin, opcode, payload) of the next server frame, or None at the end of the stream."""
        while True:
            if len(self.buf) >= 2:
                b0, b1 = self.buf[0], self.buf[1]
                assert not b1 & 0x80, "a server frame must not be masked"
                n, at = b1 & 0x7F, 2
                if n == 126 and len(self.buf) >= 4:
                    n, at = struct.unpack("!H", self.buf[2:4])[0], 4
                elif n == 127 and len(self.buf) >= 10:
                    n, at = struct.unpack("!Q", self.buf[2:10])[0], 10
                if (b1 & 0x7F) < 126 or at > 2:
                    if len(self.buf) >= at + n:
                        payload, self.buf = self.buf[at : at + n], self.buf[at + n :]
                        return bool(b0 & 0x80), b0 & 0x0F, payload
            if not self._more(deadline):
                return None


def ws_frame(opcode, payload=b"", *, fin=True, rsv=0, mask=True, key=b"\x01\x02\x03\x04",
             declared=None) -> bytes:  # fmt: skip
    """A client frame (RFC 6455 §5.2); ``declared`` lies about the payload length."""
    n = len(payload) if declared is None else declared
    head = bytes([(0x80 if fin else 0) | (rsv << 4) | opcode])
    m = 0x80 if mask else 0
    if n < 126:
        head += bytes([m | n])
    elif n < 65536:
        head += bytes([m | 126]) + struct.pack("!H", n)
    else:
        head += bytes([m | 127]) + struct.pack("!Q", n)
    if mask:
        payload = bytes(b ^ key[i % 4] for i, b in enumerate(payload))
        head += key
    return head + payload


def handshake(server, *, path="/ws", headers=None, raw_path=None) -> bytes:
    lines = [f"GET {path} HTTP/1.1".encode() if raw_path is None else b"GET " + raw_path
             + b" HTTP/1.1", f"Host: {server.host}:{server.port}".encode()]  # fmt: skip
    for k, v in headers or []:
        lines.append(k.encode("latin-1", "replace") + b": " + v.encode("latin-1", "replace"))
    return b"\r\n".join(lines) + b"\r\n\r\n"


def standard_headers(key: str, origin: str | None) -> list[tuple[str, str]]:
    out = [("Upgrade", "websocket"), ("Connection", "Upgrade"), ("Sec-WebSocket-Key", key),
           ("Sec-WebSocket-Version", "13")]  # fmt: skip
    if origin is not None:
        out.append(("Origin", origin))
    return out


def accept_for(key: str) -> str:
    return base64.b64encode(hashlib.sha1(key.encode() + GUID).digest()).decode()


def _no_nan(text):
    raise ValueError(f"non-standard JSON constant {text}")


def strict_json(payload: bytes):
    doc = json.loads(payload.decode("utf-8"), parse_constant=_no_nan)
    assert isinstance(doc, dict) and isinstance(doc.get("type"), str), doc
    return doc


def open_ws(server, *, query="", extra=()) -> tuple[Conn, dict]:
    """A well-formed, authorised connection; returns it after the server's hello."""
    key = base64.b64encode(b"0123456789abcdef").decode()
    conn = Conn(server)
    q = "?" + urllib.parse.urlencode({"token": TOKEN, **dict(query and [query] or [])})
    conn.send(handshake(server, path="/ws" + q, headers=standard_headers(key, None) + list(extra)))
    deadline = time.monotonic() + IO_TIMEOUT_S
    status, headers, body = conn.response(deadline)
    assert status == 101, (status, body)
    assert headers["sec-websocket-accept"] == accept_for(key)
    fin, opcode, payload = conn.frame(deadline)
    assert (fin, opcode) == (True, 1) and strict_json(payload)["type"] == "hello"
    return conn, headers


def after_frames(conn: Conn, client_close: int | None) -> str:
    """Ping the server after the fuzzed frames; the outcome (property checked here)."""
    probe = b"probe-" + os.urandom(4).hex().encode()
    conn.send(ws_frame(9, probe, key=b"\x10\x20\x30\x40"))
    deadline = time.monotonic() + IO_TIMEOUT_S
    while True:
        got = conn.frame(deadline)
        assert got is not None, "the server dropped the connection without a close frame"
        fin, opcode, payload = got
        if opcode == 1:  # an event pushed meanwhile
            strict_json(payload)
        elif opcode == 10 and payload == probe:
            return "alive"
        elif opcode == 8:
            code = struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else 1005
            allowed = SERVER_CLOSE_CODES | ({client_close} if client_close else set())
            assert code in allowed, f"close code {code} ({payload[2:]!r})"
            payload[2:].decode("utf-8")  # a readable reason
            return f"closed {code}"
        else:
            assert opcode in (10,), f"unexpected server frame opcode {opcode}"


# --------------------------------------------------------------------------- #
# strategies
# --------------------------------------------------------------------------- #
token_offers = st.one_of(
    st.just(TOKEN), st.just(""), st.just(TOKEN[:-1]), st.just(TOKEN.upper()),
    st.just(" " + TOKEN), st.just(TOKEN + "\x00"), st.text(max_size=30),
)  # fmt: skip
text_any = st.text(max_size=40)
machines = st.one_of(st.sampled_from(["alpha", "vm1", "nope", "", "../alpha", "a" * 3000]),
                     text_any)  # fmt: skip
origins = st.one_of(
    st.none(),
    st.sampled_from(["SELF", "http://evil.example", "null", "http://127.0.0.1:1",
                     "http://localhost", "file://", "", "http://127.0.0.1"]),
    text_any,
)  # fmt: skip
header_names = st.sampled_from(["Upgrade", "Connection", "Sec-WebSocket-Key",
                                "Sec-WebSocket-Version", "Sec-WebSocket-Protocol",
                                "Sec-WebSocket-Extensions", "Cookie", "Authorization",
                                "Origin", "Host", "Content-Length", "Transfer-Encoding",
                                "X-" + "a" * 40])  # fmt: skip
header_values = st.one_of(
    st.sampled_from(["websocket", "WebSocket", "Upgrade", "keep-alive, Upgrade", "13", "8",
                     "", "permessage-deflate; client_max_window_bits=99",
                     "permessage-deflate; server_max_window_bits", "x, y, z", "chunked",
                     "-1", "ajtwin_token=" + TOKEN, "Bearer " + TOKEN, "Bearer x",
                     "dGhlIHNhbXBsZSBub25jZQ==", "not base64", "a" * 9000]),
    text_any,
)  # fmt: skip


@st.composite
def handshakes(draw):
    """(request bytes, the right token offered?, same origin?, well-formed?)."""
    key = base64.b64encode(draw(st.binary(min_size=16, max_size=16))).decode()
    offer = draw(st.sampled_from(["query", "header", "cookie", "none"]))
    token = draw(token_offers)
    origin = draw(origins)
    query = {}
    if draw(st.booleans()):
        query["machine"] = draw(machines)
    extra = []
    if offer == "query":
        query["token"] = token
    elif offer == "header":
        extra.append(("Authorization", "Bearer " + token))
    elif offer == "cookie":
        extra.append(("Cookie", "ajtwin_token=" + token))
    well_formed = draw(st.integers(0, 3)) > 0
    headers = standard_headers(key, origin)
    if not well_formed:  # drop, replace or add headers
        for _ in range(draw(st.integers(1, 4))):
            choice = draw(st.integers(0, 2))
            if choice == 0 and headers:
                headers.pop(draw(st.integers(0, len(headers) - 1)))
            elif choice == 1 and headers:
                i = draw(st.integers(0, len(headers) - 1))
                headers[i] = (headers[i][0], draw(header_values))
            else:
                headers.append((draw(header_names), draw(header_values)))
    path = "/ws" + ("?" + urllib.parse.urlencode(query) if query else "")
    raw = None
    if draw(st.integers(0, 9)) == 0:  # a raw request line: bytes a browser never sends
        raw = draw(st.sampled_from([b"/ws?machine=\xff\xfe", b"/ws?token=%ZZ", b"/ws#x",
                                    b"/ws?" + b"a=1&" * 2000, b"//ws", b"/WS", b"*",
                                    b"/ws?machine=%00"]))  # fmt: skip
    return {
        "key": key,
        "path": path,
        "raw": raw,
        "headers": headers + extra,
        # the server strips blanks around a header's or cookie's token (HTTP does too), not
        # around the query's
        "authorised": offer != "none"
        and (token == TOKEN or (offer != "query" and token.strip() == TOKEN)),
        "well_formed": well_formed and raw is None,
    }


@st.composite
def frame_lists(draw):
    """A sequence of raw client frames; returns (bytes, the client's close code, lied?)."""
    frames, close_code, lied = [], None, False
    for _ in range(draw(st.integers(1, 5))):
        kind = draw(st.sampled_from(["text", "json", "bad_utf8", "binary", "ping", "pong",
                                     "close", "close_bad", "cont", "fragmented", "reserved",
                                     "rsv", "unmasked", "long_ping", "big", "lie"]))  # fmt: skip
        key = draw(st.binary(min_size=4, max_size=4))
        if kind == "text":
            frames.append(ws_frame(1, draw(st.text(max_size=60)).encode(), key=key))
        elif kind == "json":
            frames.append(ws_frame(1, json.dumps({"type": "subscribe", "machine": "alpha"})
                                   .encode(), key=key))  # fmt: skip
        elif kind == "bad_utf8":
            frames.append(ws_frame(1, b"ok\xff\xfe\xc0" + draw(st.binary(max_size=10)), key=key))
        elif kind == "binary":
            frames.append(ws_frame(2, draw(st.binary(max_size=200)), key=key))
        elif kind in ("ping", "pong"):
            frames.append(ws_frame(9 if kind == "ping" else 10, draw(st.binary(max_size=125)),
                                   key=key))  # fmt: skip
        elif kind == "close":
            code = draw(st.one_of(st.sampled_from([1000, 1001, 1003, 1008, 3000, 4999]),
                                  st.integers(0, 65535)))  # fmt: skip
            reason = draw(st.text(max_size=30)).encode()[:120]
            frames.append(ws_frame(8, struct.pack("!H", code) + reason, key=key))
            close_code = close_code or code
            break  # nothing may follow a close
        elif kind == "close_bad":  # a 1-byte close payload, or a reason that is not UTF-8
            frames.append(ws_frame(8, draw(st.sampled_from([b"\x03", b"\x03\xe8\xff\xfe"])),
                                   key=key))  # fmt: skip
            break
        elif kind == "cont":
            frames.append(ws_frame(0, b"orphan continuation", key=key))
        elif kind == "fragmented":
            text = draw(st.text(min_size=2, max_size=40)).encode()
            frames.append(ws_frame(1, text[:1], fin=False, key=key))
            if draw(st.booleans()):
                frames.append(ws_frame(9, b"mid", key=key))  # control frames may interleave
            frames.append(ws_frame(0, text[1:], key=key))
        elif kind == "reserved":
            frames.append(ws_frame(draw(st.sampled_from([3, 4, 5, 6, 7, 11, 12, 13, 14, 15])),
                                   b"x", key=key))  # fmt: skip
        elif kind == "rsv":
            frames.append(ws_frame(1, b"x", rsv=draw(st.integers(1, 7)), key=key))
        elif kind == "unmasked":
            frames.append(ws_frame(1, b"plain", mask=False))
        elif kind == "long_ping":
            frames.append(ws_frame(9, b"p" * 126, key=key))
        elif kind == "big":  # one message over the server's size limit
            frames.append(ws_frame(2, b"\x00" * draw(st.sampled_from([70_000, 1_100_000])),
                                   key=key))  # fmt: skip
        else:  # declares far more than it sends: the server must not wait on it forever
            frames.append(ws_frame(2, b"short", declared=draw(st.sampled_from([2**40, 2**63]))))
            lied = True
            break
    return b"".join(frames), close_code, lied


# --------------------------------------------------------------------------- #
# the socket
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("profile", WS_PROFILES)
def test_fuzz_ws_handshake(profile, server):
    self_origin = f"http://{server.host}:{server.port}"

    @settings(settings.get_profile(profile))
    @given(handshakes())
    def run(h):
        conn = Conn(server)
        try:
            headers = [(k, self_origin if v == "SELF" else v) for k, v in h["headers"]]
            conn.send(handshake(server, path=h["path"], headers=headers, raw_path=h["raw"]))
            deadline = time.monotonic() + IO_TIMEOUT_S
            status, got, body = conn.response(deadline)
            assert status < 500, (status, body)
            assert b"Traceback" not in body
            origins = [v for k, v in headers if k.lower() == "origin"]  # as finally sent
            same_origin = all(origin == self_origin for origin in origins)
            if status == 101:
                assert h["authorised"], "a websocket opened without the token"
                assert same_origin, f"a websocket opened from origin {origins!r}"
                assert got["sec-websocket-accept"] == accept_for(h["key"])
                fin, opcode, payload = conn.frame(deadline)
                assert opcode == 1 and strict_json(payload)["type"] == "hello"
            else:
                assert 400 <= status < 500, status
                if h["well_formed"] and h["authorised"] and same_origin:
                    raise AssertionError(f"a valid, authorised handshake refused: {status}")
            OUTCOMES[f"handshake {status}"] += 1
        finally:
            conn.close()
        _check_server(server)

    run()
    conn, _ = open_ws(server)  # the server still serves
    conn.close()


@pytest.mark.parametrize("profile", WS_PROFILES)
def test_fuzz_ws_frames(profile, server):
    @settings(settings.get_profile(profile))
    @given(frame_lists(), st.sampled_from(["", "alpha", "vm1"]))
    def run(frames, machine):
        data, client_close, lied = frames
        conn, _ = open_ws(server, query=("machine", machine) if machine else "")
        try:
            conn.send(data)
            if lied:  # the server waits for bytes that never come: we hang up
                OUTCOMES["lied, hung up"] += 1
            else:
                OUTCOMES[after_frames(conn, client_close)] += 1
        finally:
            conn.close()
        _check_server(server)

    run()
    conn, _ = open_ws(server, query=("machine", "vm1"))  # still serving, events flowing
    assert after_frames(conn, None) == "alive"
    deadline = time.monotonic() + 120  # the feed runs its twin first (loaded cores)
    fin, opcode, payload = conn.frame(deadline)
    while opcode != 1:
        fin, opcode, payload = conn.frame(deadline)
    assert strict_json(payload)["machine"] == "vm1"
    conn.close()


def test_many_silent_clients_do_not_pile_up(server):
    """Clients that send a message and vanish: each connection is noticed and released
    (the server reads every connection, so a lost client is found without an event)."""
    from ajtwin.web.app import MAX_WEBSOCKETS

    for k in range(MAX_WEBSOCKETS + 6):  # more than may be open at once
        conn, _ = open_ws(server)
        if k % 2:
            conn.send(ws_frame(1, b"hello from the page"))
        conn.close()  # no close frame: the client just goes
    deadline = time.monotonic() + 30  # each is released once its end is read
    while True:
        conn = Conn(server)
        key = base64.b64encode(b"0123456789abcdef").decode()
        conn.send(handshake(server, path="/ws?token=" + TOKEN, headers=standard_headers(key, None)))
        status = conn.response(time.monotonic() + IO_TIMEOUT_S)[0]
        if status == 101 or time.monotonic() > deadline:
            break
        conn.close()
        time.sleep(0.5)
    assert status == 101, "closed connections were not released"
    assert after_frames(conn, None) == "alive"
    conn.close()
    _check_server(server)


# --------------------------------------------------------------------------- #
# the events
# --------------------------------------------------------------------------- #
class Weird:
    def __repr__(self):
        return "<Weird>"


leaves = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**30), 10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=10),
    st.binary(max_size=8), st.just(np.float32(np.nan)), st.just(np.int64(7)),
    st.just(np.array([1.0, np.inf])), st.just(Weird()), st.just({1, 2}), st.just(1 + 2j),
    st.just([]), st.just({}),
)  # fmt: skip
keys = st.one_of(st.text(max_size=6), st.integers(-5, 5), st.none(), st.tuples(st.integers()))
values = st.recursive(
    leaves,
    lambda inner: st.one_of(
        st.lists(inner, min_size=1, max_size=4),  # (empty ones are leaves: every branch
        st.tuples(inner, inner),  # uses ``inner``, so hypothesis sees the recursion)
        st.dictionaries(keys, inner, min_size=1, max_size=4),
    ),  # fmt: skip
    max_leaves=12,
)
samples = st.one_of(
    st.dictionaries(st.sampled_from(["machine", "time_s", "states", "state_stds", "alarms",
                                     "measured", "nis", "type", "published_at", "x"]),
                    values, max_size=8),  # fmt: skip
    st.fixed_dictionaries({"machine": st.one_of(st.sampled_from(["m1"]), values),
                           "time_s": values}, optional={"states": values, "alarms": values}),
    values,
)  # fmt: skip


def deep(n):
    out = 1.0
    for _ in range(n):
        out = [out]
    return out


@pytest.mark.parametrize("profile", WS_PROFILES)
def test_fuzz_ws_events(profile):
    import asyncio

    from ajtwin.web.app import event_text
    from ajtwin.web.publisher import LivePublisher

    @settings(settings.get_profile(profile))
    @given(st.sampled_from(["publish", "publish_engine", "publish_link", "announce"]), samples)
    def run(how, sample):
        loop = asyncio.new_event_loop()
        try:
            pub = LivePublisher(history=5)
            sub = pub.subscribe(loop)
            try:
                if how == "publish_link":
                    pub.publish_link("m1", sample)
                else:
                    getattr(pub, how)(sample)
            except ValueError as exc:
                assert len(str(exc)) > 10, exc  # a sentence, not a bare value
                OUTCOMES[f"{how} refused"] += 1
                return
            loop.run_until_complete(asyncio.sleep(0))  # deliver call_soon_threadsafe
            sent = 0
            while not sub.queue.empty():
                text = event_text(sub.queue.get_nowait())
                doc = strict_json(text.encode())
                assert isinstance(doc.get("published_at"), float)
                assert math.isfinite(doc["published_at"])
                sent += 1
            OUTCOMES[f"{how} sent {sent}"] += 1
        finally:
            loop.close()

    run()


@pytest.mark.parametrize(
    "how, sample",
    [
        ("publish", {"machine": "m1", "time_s": 1.0, "states": {(1, 2): 3.0}}),  # tuple key
        ("publish", {"machine": "m1", "time_s": b"\xff"}),  # bytes
        ("publish", {"machine": "m1", "time_s": 1.0, "x": {1, 2}}),  # a set
        ("publish", {"machine": "m1", "time_s": 1.0, "x": Weird()}),  # any object
        ("publish", {"machine": "m1", "time_s": 1.0, "x": deep(5000)}),  # nesting
        ("publish", {"machine": "m1", "time_s": 1.0, "x": 1 + 2j}),  # complex
        ("publish", [("machine", "m1")]),  # not a dict
        (
            "publish_engine",
            {"machine": "m1", "time_s": 1.0, "cusum": {"L_w": "x"}, "window_nis_p": "x"},
        ),  # fmt: skip
        ("publish_engine", {"machine": "m1", "time_s": 1.0, "events": [1]}),
        ("publish_link", {"state": "reconnecting", "since": "x", "retry_in_s": "y"}),
        ("publish_link", {"state": "connected", "gap_s": None}),
        ("announce", {"type": "print", "machine": None, "x": np.array([np.nan])}),
        # the caller's published_at was kept (setdefault): None reached the page's clock
        ("announce", {"machine": None, "time_s": None, "published_at": None, "type": ""}),
    ],
)
def test_ws_events_that_raised(how, sample):
    """Each once raised out of the publisher or out of the websocket's json.dumps (the
    page's stream then died): now refused with a sentence or sent as strict JSON."""
    import asyncio

    from ajtwin.web.app import event_text
    from ajtwin.web.publisher import LivePublisher

    loop = asyncio.new_event_loop()
    try:
        pub = LivePublisher()
        sub = pub.subscribe(loop)
        try:
            if how == "publish_link":
                pub.publish_link("m1", sample)
            else:
                getattr(pub, how)(sample)
        except ValueError as exc:
            assert len(str(exc)) > 10
            return
        loop.run_until_complete(asyncio.sleep(0))
        assert not sub.queue.empty()
        while not sub.queue.empty():
            doc = strict_json(event_text(sub.queue.get_nowait()).encode())
            assert isinstance(doc.get("published_at"), float)  # the pages' delivery clock
    finally:
        loop.close()


# --------------------------------------------------------------------------- #
# the socket inputs that once failed (found by the fuzzers above, kept as cases)
# --------------------------------------------------------------------------- #
def _answer(server, request: bytes) -> tuple[int, bytes]:
    conn = Conn(server)
    try:
        conn.send(request)
        status, _, body = conn.response(time.monotonic() + IO_TIMEOUT_S)
        return status, body
    finally:
        conn.close()


@pytest.mark.parametrize(
    "headers, raw_path",
    [
        ([("Origin", "\x1f")], None),  # a control character in a header value
        ([("Sec-WebSocket-Key", "\x1f")], None),
        ([], b"/ws?token=" + TOKEN.encode() + b"&x=" + b"a" * 9000),  # request line too long
    ],
)
def test_refused_opening_requests_are_answered(server, headers, raw_path):
    """websockets' parser refused these and uvicorn left the client waiting forever."""
    key = base64.b64encode(b"0123456789abcdef").decode()
    names = {k for k, _ in headers}
    request = handshake(
        server,
        path="/ws?token=" + TOKEN,
        headers=[h for h in standard_headers(key, None) if h[0] not in names] + headers,
        raw_path=raw_path,
    )
    status, body = _answer(server, request)
    assert 400 <= status < 500 and len(body) > 10, (status, body)
    _check_server(server)


def test_a_page_of_another_site_cannot_open_the_websocket(server):
    """Was accepted: a page of any site could read the stream of a dashboard on
    127.0.0.1 served without a token (a websocket has no same-origin rule)."""
    key = base64.b64encode(b"0123456789abcdef").decode()
    for origin in ("http://evil.example", "null", f"http://127.0.0.1:{server.port}.evil"):
        request = handshake(server, path="/ws?token=" + TOKEN,
                            headers=standard_headers(key, origin))  # fmt: skip
        assert _answer(server, request)[0] == 403
    same = f"http://{server.host}:{server.port}"
    two = standard_headers(key, same) + [("Origin", "http://evil.example")]
    # two Origin headers (no browser sends that): websockets' parser refuses them (400)
    assert _answer(server, handshake(server, path="/ws?token=" + TOKEN, headers=two))[0] == 400
    conn, _ = open_ws(server, extra=[("Origin", same)])
    conn.close()


@pytest.mark.parametrize(
    "frame, code",
    [
        (ws_frame(1, b"", key=b"\x00\x00\x00\x00"), 1003),  # an empty text message
        (ws_frame(2, b"\x00" * 70_000), 1009),  # over the 64 KiB limit
        (ws_frame(1, b"ok\xff\xfe"), 1007),  # not UTF-8 (was a traceback in the log)
        # … and followed by a close in the same read: websockets is already closing when
        # the text is handled (the first fix raised InvalidState there: fuzz-long)
        (ws_frame(1, b"ok\xff\xfe\xc0") + ws_frame(8, struct.pack("!H", 1000)), 1000),
    ],
)
def test_messages_from_a_page_are_answered_with_a_close(server, frame, code):
    """The server stopped reading a connection after its first message (ping, close and
    a vanished client then went unnoticed); now every message gets a close frame."""
    conn, _ = open_ws(server)
    try:
        conn.send(frame)
        assert after_frames(conn, None) == f"closed {code}"
    finally:
        conn.close()


def test_open_websockets_are_capped(server):
    """At most MAX_WEBSOCKETS at once (each holds a queue of events): one more is refused
    with a 403, and a place frees when one closes."""
    from ajtwin.web.app import MAX_WEBSOCKETS

    key = base64.b64encode(b"0123456789abcdef").decode()
    request = handshake(server, path="/ws?token=" + TOKEN, headers=standard_headers(key, None))
    held = []
    try:
        deadline = time.monotonic() + 30  # earlier tests' sockets may still be closing
        while len(held) < MAX_WEBSOCKETS and time.monotonic() < deadline:
            conn = Conn(server)
            conn.send(request)
            if conn.response(time.monotonic() + IO_TIMEOUT_S)[0] == 101:
                held.append(conn)
            else:
                conn.close()
                time.sleep(0.2)
        assert len(held) == MAX_WEBSOCKETS
        assert _answer(server, request)[0] == 403
        held.pop().close()
        deadline = time.monotonic() + 30
        while (status := _answer(server, request)[0]) != 101 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert status == 101
    finally:
        for conn in held:
            conn.close()
