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

from ajtwin.engine.fleet import LiveEngine  # noqa: E402
from ajtwin.engine.messages import StepMessage
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


def follow(url: str, store, *, within_s: float, **link_options):
    """Follow machine m1 with a live engine on ``store`` until its print is stored (or
    ``within_s``); returns (link, registry, how often another task of the event loop ran
    while fed rows were still queued)."""
    registry = Registry(store)
    engine = LiveEngine(registry)
    engine.warm_up()
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
