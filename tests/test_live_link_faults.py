"""The live twin's OPC UA link against a machine that misbehaves: a clock that goes back, a
print state that is no state, a server that never answers, a 100,000-row burst.

The machine is ``tests/opcua_machine.py`` in its own process on 127.0.0.1 and a free port,
stopped by its PID; the link runs in this process; every wait is bounded.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("asyncua")

from asyncua import ua  # noqa: E402

from ajtwin.engine.fleet import LiveEngine  # noqa: E402
from ajtwin.engine.messages import LinkMessage, StepMessage
from ajtwin.engine.stream import TwinStream  # noqa: E402
from ajtwin.estimation.online import OnlineTwin  # noqa: E402
from ajtwin.estimation.samples import Sample  # noqa: E402
from ajtwin.live.link import (  # noqa: E402
    OpcUaLink,
    OpcUaLogin,
    RowQueue,
    fault_text,
    new_rows,
    print_state,
    subscription_status_text,
)
from ajtwin.simulation import simulate  # noqa: E402
from ajtwin.store.registry import Registry  # noqa: E402

HERE = Path(__file__).resolve().parent
SRC = str(HERE.parent / "src")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Machine:
    """``tests/opcua_machine.py MODE PORT ROWS`` in a child process (stopped by its PID)."""

    def __init__(self, mode: str, rows: int = 240, startup_s: float = 180.0, attempts: int = 2):
        for _attempt in range(attempts):  # a free port can be taken before the child binds it
            self.port = _free_port()
            self.url = f"opc.tcp://127.0.0.1:{self.port}"
            said = self._start(mode, rows, startup_s)
            if said is None:
                return
        raise RuntimeError(f"the scripted machine ({mode}) did not start: {said[-2000:]}")

    def _start(self, mode, rows, startup_s) -> str | None:
        """Start the child and wait (bounded) for its "up"; None, or what it said instead."""
        env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
        env["JAX_PLATFORMS"] = "cpu"
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE / "opcua_machine.py"), mode, str(self.port), str(rows)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            bufsize=0,  # unbuffered: a line read ahead into a buffer is one select never sees
        )
        deadline = time.monotonic() + startup_s
        said = b""
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.proc.stdout], [], [], 1.0)
            if ready:
                line = self.proc.stdout.readline()
                if line.strip() == b"up":
                    return None
                said += line
                if not line and self.proc.poll() is not None:
                    break
        self.stop()
        return said.decode(errors="replace")

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=20)
        if not self.proc.stdout.closed:
            self.proc.stdout.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def follow(url: str, store, *, within_s: float, messages: list | None = None, **link_options):
    """Follow machine m1 with a live engine on ``store`` until its print is stored (or
    ``within_s``); returns (link, registry, how often another task of the event loop ran
    while fed rows were still queued). ``messages`` gets the engine's messages."""
    registry = Registry(store)
    engine = LiveEngine(registry)
    engine.warm_up()
    if messages is not None:
        engine.subscribe(messages.append)
    link = OpcUaLink(url, ["m1"], engine, **link_options)
    beats = [0]

    async def heartbeat(stop):
        while not stop.is_set():
            await asyncio.sleep(0.05)
            beats[0] += bool(link._unfed or any(len(q) for q in link.queues.values()))

    async def main():
        stop = asyncio.Event()
        beat = asyncio.create_task(heartbeat(stop))
        task = asyncio.create_task(link.run(stop))
        try:
            await asyncio.wait_for(asyncio.shield(task), within_s)
        except TimeoutError:
            stop.set()
            await asyncio.wait_for(task, 30)
        finally:
            stop.set()
            await beat

    try:
        asyncio.run(main())
    finally:
        engine.shutdown()
    return link, registry, beats[0]


# ------------------------------------------------------------------ pure pieces
def _rows(times):
    return np.array([[t, 375, 23, 50, 70, 8, 5800, 5780, 1.2e-8] for t in times], float)


def test_new_rows_after_the_previous_buffer_and_back_in_time():
    first = _rows([1, 2, 3])
    taken, tail, dropped, _, problems = new_rows("m1", first, None, -np.inf)
    assert taken[:, 0].tolist() == [1, 2, 3] and dropped.size == 0 and not problems
    # the next buffer: 2, 3 are its overlap with the first; 1.5 and 0 went back in time
    second = _rows([2, 3, 4, 1.5, 0, 5])
    taken, tail, dropped, after, _ = new_rows("m1", second, tail, 3.0)
    assert taken[:, 0].tolist() == [4, 5] and dropped.tolist() == [1.5, 0] and after == 4.0
    # the same buffer again (a repeated notification): nothing new, nothing reported again
    taken, _, dropped, _, _ = new_rows("m1", second, tail, 5.0)
    assert taken.size == 0 and dropped.size == 0
    # without the previous last row (a reconnection) the old rows are its overlap, silently
    taken, _, dropped, _, _ = new_rows("m1", _rows([3, 4, 5, 6]), None, 5.0)
    assert taken[:, 0].tolist() == [6] and dropped.size == 0


def test_a_queue_gives_its_rows_in_slices():
    queue = RowQueue()
    queue.append(_rows(range(5)))
    queue.append(_rows(range(5, 8)))
    assert len(queue) == 8
    assert queue.take(3)[:, 0].tolist() == [0, 1, 2]
    assert queue.take(4)[:, 0].tolist() == [3, 4, 5, 6]
    assert queue.take(4)[:, 0].tolist() == [7] and len(queue) == 0 and not queue


def test_a_clock_back_to_zero_is_a_new_print_only_on_a_machine_without_print_id(caplog):
    """Buffers as a link receives them: 200 s of print, then a buffer whose clock began
    again at 0. Without a PrintId that is a restarted machine's new print (a boundary in
    the queue); with a PrintId that did not change it is a server continuing the same print
    from an earlier second, and those rows are dropped as going back."""
    from types import SimpleNamespace

    def link(print_id):
        link = OpcUaLink("opc.tcp://127.0.0.1:4840", ["m1"], SimpleNamespace(sessions={}))
        if print_id:
            link.print_ids["m1"] = print_id
        link._enqueue("m1", _rows(range(200)).ravel().tolist())
        link._enqueue("m1", _rows([*range(150, 200), *range(0, 10)]).ravel().tolist())
        return link

    with caplog.at_level(logging.WARNING, logger="ajtwin.live"):
        queue = link(None).queues["m1"]
        assert queue.has_new_print() and len(queue) == 210
        assert "its clock went back from t = 199 s to t = 0 s" in caplog.text
        caplog.clear()
        queue = link("p1").queues["m1"]
        assert not queue.has_new_print() and len(queue) == 200
        assert "time went backwards" in caplog.text and "new print" not in caplog.text


def test_print_state_must_be_one_of_its_texts(caplog):
    with caplog.at_level(logging.WARNING, logger="ajtwin.live"):
        assert print_state("m1", 3.14, "printing") == "printing"
        assert print_state("m1", "", "printing") == "printing"
        assert print_state("m1", " Finished ", "printing") == "finished"
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == (
        "m1: PrintState = 3.14 is not a print state (printing or finished); ignored, the print "
        "stays printing"
    )
    assert len(lines) == 2


def test_a_timeout_is_said_in_words():
    text = fault_text(TimeoutError(), "opc.tcp://127.0.0.1:4840", 4.0)
    assert text.startswith("no answer from opc.tcp://127.0.0.1:4840 within 4 s (TimeoutError)")
    assert "TimeoutError: " not in text
    assert "connection refused" in fault_text(ConnectionRefusedError(111, ""), "u", 1.0)


# ------------------------------------------------------------------ against a machine
def test_a_lost_subscription_is_said_in_words():
    """The server's last word on a subscription (asyncua hands a StatusChangeNotification)
    is logged and published by name and meaning, not as ``StatusCode(value=2148270080)``."""
    url = "opc.tcp://127.0.0.1:4840"
    shutdown = ua.StatusChangeNotification(Status=ua.StatusCode(ua.StatusCodes.BadShutdown))
    said = fault_text(ConnectionError(subscription_status_text(shutdown)), url, 4.0)
    assert said == (
        "the subscription ended: BadShutdown: the server stopped, is restarting or no longer "
        "answers"
    )
    # a code without words of our own: its OPC UA name and description
    timeout = ua.StatusChangeNotification(Status=ua.StatusCode(ua.StatusCodes.BadTooManyOperations))
    said = fault_text(ConnectionError(subscription_status_text(timeout)), url, 4.0)
    assert said.startswith("the subscription ended: BadTooManyOperations: ")
    assert len(said) > len("the subscription ended: BadTooManyOperations: ") + 10
    # a service call refused with a status code
    said = fault_text(ua.UaStatusCodeError(ua.StatusCodes.BadSessionIdInvalid), url, 4.0)
    assert said == "BadSessionIdInvalid: the server no longer knows this session (it restarted)"
    assert "StatusCode(value=" not in said


def test_samples_whose_time_goes_back_are_dropped_with_a_line_and_no_false_alarm(tmp_path, caplog):
    """exp1 seed 1 with samples 100-129 stamped 100, 97, … 13 s: they are dropped and said
    so (how many, which times), the 29 s they leave are missing data, and the stored print
    has no alarm (the twin re-acquiring after the gap is not a fault)."""
    with Machine("back") as m, caplog.at_level(logging.INFO, logger="ajtwin.live"):
        link, registry, _ = follow(m.url, tmp_path / "r.sqlite", within_s=240)
    assert "m1" in link.finished
    counts = [
        int(n)
        for n in re.findall(r"m1: (\d+) sample\(s\) whose time went backwards dropped", caplog.text)
    ]
    assert sum(counts) == 29, caplog.text
    assert re.search(r"t = 97(, 94)?.* s, after t = 100 s\)", caplog.text), caplog.text
    printed = registry.last_print("m1")
    assert printed is not None and printed["n_samples"] == 240
    assert registry.anomalies("m1").empty, registry.anomalies("m1").to_dict("records")


def test_a_print_state_that_is_no_state_is_logged_and_the_print_still_stored(tmp_path, caplog):
    with Machine("statebad") as m, caplog.at_level(logging.WARNING, logger="ajtwin.live"):
        link, registry, _ = follow(m.url, tmp_path / "r.sqlite", within_s=240)
    assert "m1: PrintState = 3.14 is not a print state" in caplog.text
    assert "m1" in link.finished and registry.last_print("m1")["n_samples"] == 240


def test_a_server_that_never_answers_is_said_in_words(tmp_path):
    """An empty TimeoutError was logged and published as "TimeoutError: "."""
    with Machine("silent") as m:
        link, _, _ = follow(
            m.url, tmp_path / "r.sqlite", within_s=8, login=OpcUaLogin(timeout_s=1.0),
            max_backoff_s=0.5,
        )  # fmt: skip
    assert link.reconnects >= 1
    # the log line's text (the dashboard's link state carries the same reason)
    assert link.status.startswith(
        f"disconnected (no answer from {m.url} within 1 s (TimeoutError): the server accepts "
        "the connection but does not answer OPC UA, or it is hung); reconnecting in"
    ), link.status


def _burst(tmp_path, rows: int, within_s: float):
    """A burst of ``rows`` rows in one SampleBuffer value, followed to its stored print;
    the link (its session never lost) after checking the feeding gave the event loop back
    (keep-alives, notifications) while rows of the burst were still queued."""
    with Machine("burst", rows=rows) as m:
        link, registry, beats = follow(m.url, tmp_path / "r.sqlite", within_s=within_s)
    assert "m1" in link.finished, "the print's end was never seen"
    assert link.reconnects == 0  # the OPC UA session stayed alive
    assert registry.last_print("m1")["n_samples"] == rows
    # fed a slice at a time: the loop ran other tasks between slices, the rows still queued
    assert link.slices_cut >= 1 and beats >= 1, (link.slices_cut, beats)
    return link


def test_a_burst_is_fed_in_slices_without_starving_the_link(tmp_path):
    """3,000 rows (several seconds of filter steps, the budget a quarter second a slice)."""
    _burst(tmp_path, 3000, within_s=300)


@pytest.mark.slow
def test_a_100000_row_burst_is_fed_in_slices_and_the_print_stored(tmp_path):
    """The print's end still holds the loop while it is stored in one transaction (the
    final EM, the last part, the live rows deleted): ~7 s for 100,000 steps on 2 busy
    cores (`link.longest_slice_s` after the run), inside an OPC UA session's timeout."""
    _burst(tmp_path, 100_000, within_s=1800)


def test_samples_held_while_em_ran_are_committed_a_slice_per_poll_in_order():
    """A burst that arrived while EM ran is not replayed in one call (2.8 s for 1,000 held
    samples blocked a live link's event loop): a poll commits at most REPLAY_STEPS of them,
    and every step is committed once, in order."""
    record = simulate("exp1", seed=2, duration_min=8)
    rows = list(zip(record.time_s, record.inputs, record.outputs, strict=True))
    stream = TwinStream.new("m", twin_overrides={"window_s": 60, "every_s": 30})
    messages, k = [], 0
    core = stream.core
    while core._em_future is None:  # up to the first EM, launched in a worker
        messages += stream.feed(Sample(*rows[k]))
        k += 1
    for row in rows[k : k + 300]:  # a burst while EM runs: held, provisional
        messages += stream.feed(Sample(*row))
    k += 300
    if core._em_future is not None:
        core._em_future.result()
    before = stream.n_committed
    messages += stream.poll()
    assert 0 < stream.n_committed - before <= OnlineTwin.REPLAY_STEPS
    while core._held or core._em_future is not None:
        messages += stream.poll(wait=True)
    for row in rows[k:]:
        messages += stream.feed(Sample(*row))
    messages += stream.finish()
    steps = [m.step for m in messages if isinstance(m, StepMessage) and not m.provisional]
    assert steps == list(range(len(rows)))


def test_a_machine_restarted_mid_print_ends_the_print_and_opens_a_new_one(tmp_path, caplog):
    """The machine's server stops 120 s into its print (the client's subscription ends with
    BadShutdown) and comes back 1.5 s later printing again from t = 0 (180 s, no PrintId:
    its clock alone tells). The print followed so far is stored as it was and the new one
    as a print of its own — never one print stitched from two runs with the new run's
    first minutes dropped as "time went backwards" — and the lost subscription is said in
    words, not as a raw status number."""
    with Machine("restart", rows=120) as m, caplog.at_level(logging.INFO, logger="ajtwin.live"):
        link, registry, _ = follow(m.url, tmp_path / "r.sqlite", within_s=240)
    assert "m1" in link.finished, caplog.text
    prints = registry.prints("m1")
    assert [p["n_samples"] for p in prints] == [120, 180], (prints, caplog.text)
    assert link.new_prints == 1
    assert "time went backwards" not in caplog.text
    assert re.search(r"m1: the machine began a new print \(its clock went back from t = 119 s "
                     r"to t = 0 s", caplog.text), caplog.text  # fmt: skip
    assert "StatusCode(value=" not in caplog.text
    assert "BadShutdown: the server stopped, is restarting" in caplog.text, caplog.text


def test_a_new_print_id_ends_the_print_and_opens_a_new_one(tmp_path, caplog):
    """The machine's PrintId goes from p1 to p2 after 40 samples and a new print begins at
    t = 0: its clock went back only 39 s (too little to tell a new print by the clock), so
    the PrintId alone says it. Two prints are stored, none of the new one's samples dropped
    as "time went backwards"."""
    with Machine("newid", rows=40) as m, caplog.at_level(logging.INFO, logger="ajtwin.live"):
        link, registry, _ = follow(m.url, tmp_path / "r.sqlite", within_s=180)
    assert "m1" in link.finished, caplog.text
    assert [p["n_samples"] for p in registry.prints("m1")] == [40, 60], caplog.text
    assert link.new_prints == 1 and link.print_ids == {"m1": "p2"}
    assert "time went backwards" not in caplog.text
    assert "m1: the machine began a new print (its PrintId changed from 'p1' to 'p2')" in (
        caplog.text
    )


def test_a_twin_that_joins_a_print_late_says_how_much_it_missed(tmp_path, caplog):
    """The print began 200 s before the twin's first sample (the machine's buffer no longer
    holds its start): the link says so in words, once, and publishes ``missed_s`` on the
    link state the dashboard shows."""
    messages: list = []
    with Machine("late", rows=60) as m, caplog.at_level(logging.INFO, logger="ajtwin.live"):
        link, registry, _ = follow(m.url, tmp_path / "r.sqlite", within_s=180, messages=messages)
    assert "m1" in link.finished, caplog.text
    (stored,) = registry.prints("m1")
    assert stored["n_samples"] == 60
    said = [r.getMessage() for r in caplog.records if "joined this print" in r.getMessage()]
    assert said == [
        "m1: joined this print 3.3 min after its start (first sample t = 200 s): the first "
        "3.3 min were printed before the twin connected and are no longer in the machine's "
        "buffer (300 samples); the twin starts from there. Start the twin before the print "
        "(`printer serve --wait-for-client` holds a virtual print until it connects)"
    ]
    missed = [m.link.missed_s for m in messages if isinstance(m, LinkMessage) and m.link.missed_s]
    assert missed == [200.0]
    # the dashboard's sentence for that link state
    from ajtwin.web.publisher import link_text

    link_state = next(m.link for m in messages if isinstance(m, LinkMessage) and m.link.missed_s)
    assert link_text(link_state.to_dict()).endswith(
        "joined the print 3.3 min after its start: the first 3.3 min were not seen"
    )


def test_the_live_dashboard_keeps_serving_after_the_print_and_says_the_link_ended(
    tmp_path, monkeypatch
):
    """``ajtwin live --opcua … --dashboard 0``: when the print ends the command keeps the
    dashboard up (the page stays, it does not fall to "reconnecting" forever) and the
    machine's link state says the link ended, until Ctrl-C; then the port is closed."""
    import json
    import urllib.request

    from click.testing import CliRunner

    import ajtwin.cli.live as live_cli

    seen = {}

    def get(url):
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read().decode()

    def look_then_ctrl_c():  # the wait after the print: look at the page once, then "Ctrl-C"
        seen["page"] = get(seen["url"] + "machine/m1")
        seen["api"] = json.loads(get(seen["url"] + "api/machine/m1")[1])
        raise KeyboardInterrupt

    real_echo = live_cli.click.echo

    def echo(message=None, *args, **kwargs):
        if message and "dashboard still at " in str(message):
            seen["url"] = str(message).split("dashboard still at ")[1].split(";")[0]
        return real_echo(message, *args, **kwargs)

    monkeypatch.setattr(live_cli, "_wait_until_interrupted", look_then_ctrl_c)
    monkeypatch.setattr(live_cli.click, "echo", echo)
    with Machine("burst", rows=60) as m:
        args = ["--machine", "m1", "--opcua", m.url, "--store", str(tmp_path / "r.sqlite"),
                "--dashboard", "0", "--max-backoff", "1"]  # fmt: skip
        result = CliRunner().invoke(live_cli.live, args)
    assert result.exit_code == 0, result.output
    assert "followed m1 to the end of their prints" in result.output
    assert f"dashboard still at {seen['url']}; Ctrl-C stops it" in result.output
    assert "stopped (the prints had ended and are stored)" in result.output
    status, _ = seen["page"]
    assert status == 200
    api = seen["api"]
    assert api["link"]["state"] == "ended"
    assert api["link"]["text"] == "link closed (prints finished)"
    assert len(api["prints"]) == 1 and len(api["live"]["samples"]) == 60
    port = int(seen["url"].rsplit(":", 1)[1].strip("/"))
    with socket.socket() as s:  # stopped after Ctrl-C
        s.settimeout(2)
        assert s.connect_ex(("127.0.0.1", port)) != 0
