"""The live twin over OPC UA on loopback: virtual printer server → ``ajtwin live``.

Servers bind 127.0.0.1 on a free port, are stopped by their own PID, and every wait is
bounded in time.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

asyncua = pytest.importorskip("asyncua")

SRC = str(Path(__file__).resolve().parents[1] / "src")
ONSET_S = 240.0  # --fault-onset-min 4


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ajtwin(*args, log_path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-m", "ajtwin.cli", *args],
        stdout=log_path.open("w"),
        stderr=subprocess.STDOUT,
        env=env,
    )


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, sig)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=20)


def _serve(url, log_path, *extra):
    return _ajtwin(
        "printer",
        "serve",
        "--scenario",
        "nozzle_clog",
        "--speed",
        "30",
        "--duration-min",
        "7",
        "--fault-onset-min",
        str(ONSET_S / 60),
        "--endpoint",
        url,
        *extra,
        log_path=log_path,
    )


async def _collect_events(url: str, events: list, done: asyncio.Event, timeout_s: float):
    """A second client: subscribe to the server's twin alarm events until ``done``."""
    from asyncua import Client

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            async with Client(url, timeout=4) as client:
                idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                etype = await client.nodes.base_event_type.get_child(f"{idx}:TwinAlarmEventType")

                class Handler:
                    def event_notification(self, event):
                        events.append(event)

                sub = await client.create_subscription(50, Handler())
                await sub.subscribe_events(client.nodes.server, etype)
                while not done.is_set() and time.monotonic() < deadline:
                    await asyncio.sleep(0.2)
                await asyncio.sleep(1.0)  # the last notifications
                return
        except (OSError, TimeoutError, asyncua.ua.UaError):
            await asyncio.sleep(0.5)


def test_live_twin_raises_clog_alarm_over_opcua(tmp_path):
    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    store = tmp_path / "registry.sqlite"
    messages = tmp_path / "messages.jsonl"
    live = _ajtwin(
        "live",
        "--machine",
        "aj300-01",
        "--opcua",
        url,
        "--store",
        str(store),
        "--messages",
        str(messages),
        "--max-backoff",
        "1",
        log_path=tmp_path / "live.log",
    )
    server = _serve(url, tmp_path / "server.log")
    events: list = []
    try:

        async def main():
            done = asyncio.Event()
            collector = asyncio.create_task(_collect_events(url, events, done, 240))
            deadline = time.monotonic() + 240
            while live.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.5)
            done.set()
            await collector

        asyncio.run(main())
        log = (tmp_path / "live.log").read_text()
        assert live.returncode == 0, log
    finally:
        _stop(live)
        _stop(server)

    lines = [json.loads(line) for line in messages.read_text().splitlines()]
    raised = [e for m in lines for e in m.get("events", []) if e["state"] == "raised"]
    assert raised, "no alarm"
    first = raised[0]
    assert first["cause"] == "nozzle_clog"
    assert ONSET_S <= first["detected_s"] <= ONSET_S + 60
    # the second client got it as an OPC UA event
    causes = [(e.Machine, e.Cause, e.AlarmState) for e in events]
    assert ("aj300-01", "nozzle_clog", "raised") in causes

    # the registry holds the print; batch twin on the recorded samples gives the same states
    from ajtwin.estimation import Twin
    from ajtwin.store.registry import Registry

    registry = Registry(store)
    last = registry.last_print("aj300-01")
    arrays = registry.print_arrays(last["id"])
    run = Twin.default().run(
        inputs=arrays["inputs"], measurements=arrays["measurements"], time_s=arrays["time_s"]
    )
    committed = [m for m in lines if "step" in m and not m["provisional"]]
    means = np.array([list(m["states"].values()) for m in committed])
    assert [m["step"] for m in committed] == list(range(len(run.means)))
    assert (np.abs(means - run.means) / np.abs(run.means)).max() < 1e-9
    assert len(arrays["time_s"]) >= 300
    assert registry.anomalies("aj300-01")["cause"].iloc[0] == "nozzle_clog"


# --------------------------------------------------------------------------- #
# Security, in-process (one server, several clients)
# --------------------------------------------------------------------------- #


def test_security_refusals_and_setpoints(tmp_path):
    from asyncua import Client, ua

    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.live.link import LinkRefused, OpcUaLink, OpcUaLogin
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine, ensure_certificate

    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    server_cert, server_key = tmp_path / "server.der", tmp_path / "server.pem"
    client_cert, client_key = tmp_path / "client.der", tmp_path / "client.pem"
    other_cert, other_key = tmp_path / "other.der", tmp_path / "other.pem"
    trusted = tmp_path / "trusted"
    trusted.mkdir()

    async def main():
        await ensure_certificate(server_cert, server_key, "127.0.0.1", "urn:ajtwin:virtual-printer")
        await ensure_certificate(client_cert, client_key, "localhost", "urn:ajtwin:live-client")
        await ensure_certificate(other_cert, other_key, "localhost", "urn:ajtwin:live-client")
        (trusted / "client.der").write_bytes(client_cert.read_bytes())
        machine = VirtualMachine("m1", "exp1", seed=1, speed=1.0, duration_min=30)
        server = PrinterServer(
            url,
            [machine],
            users={"operator": "s3cret"},
            certificate=server_cert,
            private_key=server_key,
            trusted=trusted,
        )
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(server.serve(stop, ready.set))
        await asyncio.wait_for(ready.wait(), 120)
        security = "Basic256Sha256_SignAndEncrypt"

        def link(**kw):
            login = OpcUaLogin(timeout_s=4, **kw)
            return OpcUaLink(url, ["m1"], LiveEngine(asynchronous=False), login=login)

        try:
            # no encryption: the server offers none
            with pytest.raises(LinkRefused):
                await asyncio.wait_for(link(username="operator", password="s3cret").run(), 60)
            # encrypted, wrong password
            with pytest.raises(LinkRefused, match="user name or password"):
                await asyncio.wait_for(
                    link(
                        username="operator",
                        password="wrong",
                        security=security,
                        certificate=client_cert,
                        private_key=client_key,
                    ).run(),
                    60,
                )
            # encrypted with a certificate the server does not trust
            with pytest.raises(LinkRefused):
                await asyncio.wait_for(
                    link(
                        username="operator",
                        password="s3cret",
                        security=security,
                        certificate=other_cert,
                        private_key=other_key,
                    ).run(),
                    60,
                )
            # accepted: encrypted, trusted certificate, right password; writes a set-point
            client = Client(url, timeout=4)
            client.set_user("operator")
            client.set_password("s3cret")
            client.application_uri = "urn:ajtwin:live-client"
            await client.set_security_string(
                f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}"
            )
            async with client:
                idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                node = client.get_node(
                    ua.NodeId("m1/Monitoring/SetPoints/CarrierFlowSetpoint", idx)
                )
                await node.write_value(27.0)
                for _ in range(100):  # bounded: the server applies it in an executor
                    if machine.schedule:
                        break
                    await asyncio.sleep(0.1)
                minute, value = machine.schedule["carrier_flow_sccm"][-1]
                assert value == 27.0
                applied = round(minute * 60)
                for _ in range(100):  # bounded: until the print is 2 s past the change
                    if machine.printer.k > applied + 2:
                        break
                    await asyncio.sleep(0.1)
                assert np.isclose(machine.record.data["carrier_flow_sccm"].iloc[-1], 27.0, atol=1)
                assert np.all(machine.printer.schedule[applied:, 1] == 27.0)
                assert np.all(machine.printer.schedule[:applied, 1] == 23.0)
                # out of the machine's limits: refused, value restored
                await node.write_value(80.0)
                for _ in range(100):
                    if await node.read_value() != 80.0:
                        break
                    await asyncio.sleep(0.1)
                assert await node.read_value() == 27.0
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)

    asyncio.run(main())


def test_anonymous_cannot_write_setpoints_but_may_publish_health(tmp_path):
    from asyncua import Client, ua

    from ajtwin.live.printer_server import PrinterServer, VirtualMachine

    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"

    async def main():
        machine = VirtualMachine("m1", "exp1", seed=1, speed=1.0, duration_min=30)
        server = PrinterServer(url, [machine])
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(server.serve(stop, ready.set))
        await asyncio.wait_for(ready.wait(), 120)
        try:
            async with Client(url, timeout=4) as client:
                idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                setpoint = client.get_node(
                    ua.NodeId("m1/Monitoring/SetPoints/CarrierFlowSetpoint", idx)
                )
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await setpoint.write_value(25.0)
                status = client.get_node(ua.NodeId("m1/Monitoring/Health/Status", idx))
                await status.write_value("ok")
                assert await status.read_value() == "ok"
                eu = client.get_node(ua.NodeId("m1/Monitoring/Process/CarrierPressure/EU", idx))
                assert (await eu.read_value()).DisplayName.Text == "Pa"
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)

    asyncio.run(main())


def test_wait_for_client_holds_the_print_at_its_start_until_a_twin_subscribes(tmp_path, caplog):
    """``printer serve --wait-for-client``: the server is up but its print waits at t = 0
    until a client subscribes (a client that only reads does not start it). Two seconds of
    waiting at x60 would otherwise be two minutes of print the twin never sees; the twin that
    then connects stores the whole print, from t = 0."""
    import logging

    from asyncua import Client, ua

    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.live.link import OpcUaLink, OpcUaLogin
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine
    from ajtwin.store.registry import Registry

    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    registry = Registry(tmp_path / "r.sqlite")
    engine = LiveEngine(registry)
    engine.warm_up()

    async def main():
        machine = VirtualMachine("m1", "exp1", seed=1, speed=60.0, duration_min=2)
        server = PrinterServer(url, [machine], wait_for_client=True)
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(server.serve(stop, ready.set))
        await asyncio.wait_for(ready.wait(), 120)
        try:
            await asyncio.sleep(2.0)  # two minutes of print at x60, had it started
            async with Client(url, timeout=4) as client:
                idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                node = client.get_node(ua.NodeId("m1/Monitoring/Process/SampleTime", idx))
                assert await node.read_value() == -1.0  # nothing printed yet
            assert machine.printer.k == 0
            link = OpcUaLink(url, ["m1"], engine, login=OpcUaLogin(timeout_s=4))
            await asyncio.wait_for(link.run(), 120)
            assert link.finished == {"m1"}
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)

    try:
        with caplog.at_level(logging.INFO):  # ajtwin.live and ajtwin.printer
            asyncio.run(main())
    finally:
        engine.shutdown()
    time_s = registry.print_arrays(registry.last_print("m1")["id"])["time_s"]
    assert time_s[0] == 0.0 and len(time_s) == 120, caplog.text
    assert "joined this print" not in caplog.text
    assert "a client subscribed: the prints start" in caplog.text


def _steps_in(path: Path) -> int:
    if not path.exists():
        return 0
    return sum(1 for line in path.read_text().splitlines() if '"step"' in line)


def _wait(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.slow
def test_client_kill_and_server_restart_lose_nothing(tmp_path):
    from ajtwin.estimation import Twin
    from ajtwin.store.registry import Registry

    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    store = tmp_path / "registry.sqlite"

    def start_live(n):
        return _ajtwin(
            "live",
            "--machine",
            "aj300-01",
            "--opcua",
            url,
            "--store",
            str(store),
            "--messages",
            str(tmp_path / f"messages{n}.jsonl"),
            "--max-backoff",
            "1",
            log_path=tmp_path / f"live{n}.log",
        )

    # the restarted server continues the same print: it serves the same PrintId
    server = _serve(url, tmp_path / "server1.log", "--duration-min", "15", "--print-id", "p1")
    live = start_live(1)
    procs = [server, live]
    try:

        def stored_steps():
            if not store.exists():
                return 0
            # read through the registry: a LiveLog would claim the machine for this process
            with Registry(store, create=False) as reader:
                session = reader.live_session_of("aj300-01")
                return 0 if session is None else reader.live_n_steps(session["id"])

        _wait(lambda: stored_steps() >= 60, 180, "first committed steps")
        os.kill(live.pid, signal.SIGKILL)  # mid-print, no goodbye
        live.wait(timeout=20)
        log = Registry(store, create=False)
        session = log.live_session_of("aj300-01")
        committed = log.live_states(session["id"])
        assert len(committed) >= 60
        live = start_live(2)
        procs.append(live)
        _wait(lambda: _steps_in(tmp_path / "messages2.jsonl") >= 20, 180, "resumed steps")
        # while the print runs the open session holds its rows: nothing committed changed
        assert log.live_states(session["id"])[: len(committed)] == committed
        # the server goes away and comes back later in the same print
        lines = (tmp_path / "messages2.jsonl").read_text().splitlines()
        t_stop = json.loads([x for x in lines if '"step"' in x][-1])["time_s"]  # not a link line
        _stop(server)
        time.sleep(3)
        server = _serve(
            url, tmp_path / "server2.log", "--duration-min", "15", "--start-s", str(t_stop + 60),
            "--print-id", "p1",
        )  # fmt: skip
        procs.append(server)
        _wait(lambda: live.poll() is not None, 240, "the end of the print")
        assert live.returncode == 0, (tmp_path / "live2.log").read_text()
        assert "reconnecting" in (tmp_path / "live2.log").read_text()
    finally:
        for p in procs:
            _stop(p)

    # the session ended with its print stored: its per-step rows went with that
    # transaction; what the second process committed is what it published (messages2)
    registry = Registry(store)
    stored = registry.last_print("aj300-01")
    (closed,) = [s for s in log.live_sessions("aj300-01") if s["id"] == session["id"]]
    assert (closed["status"], closed["print_id"]) == ("closed", stored["id"])
    assert log.live_n_steps(session["id"]) == 0
    lines = (tmp_path / "messages2.jsonl").read_text().splitlines()
    published = [json.loads(x) for x in lines if '"step"' in x]
    resumed = [m for m in published if not m.get("provisional")]
    states = committed + resumed
    assert [m["step"] for m in states] == list(range(len(states)))  # nothing lost, twice
    arrays = registry.print_arrays(stored["id"])
    assert len(arrays["time_s"]) == 15 * 60 == len(states)
    run = Twin.default().run(
        inputs=arrays["inputs"], measurements=arrays["measurements"], time_s=arrays["time_s"]
    )
    means = np.array([list(m["states"].values()) for m in states])  # float64, as published
    assert (np.abs(means - run.means) / np.abs(run.means)).max() < 1e-9


@pytest.mark.slow
def test_fleet_of_printers_followed_by_one_process(tmp_path):
    port = _free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    store = tmp_path / "registry.sqlite"
    names = ["aj300-01", "aj300-02", "aj300-03"]
    server = _serve(url, tmp_path / "server.log", "--machines", "3")
    args = []
    for name in names:
        args += ["--machine", name]
    live = _ajtwin(
        "live",
        *args,
        "--opcua",
        url,
        "--store",
        str(store),
        "--messages",
        str(tmp_path / "m.jsonl"),
        "--max-backoff",
        "1",
        log_path=tmp_path / "live.log",
    )
    try:
        _wait(lambda: live.poll() is not None, 300, "the end of the prints")
        assert live.returncode == 0, (tmp_path / "live.log").read_text()
    finally:
        _stop(live)
        _stop(server)
    from ajtwin.store.registry import Registry

    registry = Registry(store)
    lines = [json.loads(x) for x in (tmp_path / "m.jsonl").read_text().splitlines()]
    for name in names:
        assert registry.last_print(name)["n_samples"] >= 300
        raised = [
            e
            for m in lines
            if m.get("machine") == name
            for e in m.get("events", [])
            if e["state"] == "raised"
        ]
        assert raised and raised[0]["cause"] == "nozzle_clog", name


@pytest.mark.slow
def test_demo_live(tmp_path):
    """``ajtwin demo --live``: the alarm, and the dashboard served live while it prints."""
    import urllib.error
    import urllib.request

    from ajtwin.web.server import free_port

    port = free_port()
    base = f"http://127.0.0.1:{port}/"
    demo = _ajtwin("demo", "--live", "--out", str(tmp_path / "out"), "--port", str(port),
                   log_path=tmp_path / "demo.log")  # fmt: skip

    def get(path):
        try:
            with urllib.request.urlopen(base + path, timeout=5) as r:
                return r.status, r.read()
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            return None, b""

    seen_printing = None
    fleet_page = b""
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and demo.poll() is None:
            status, body = get("api/fleet")
            if status == 200:
                machines = {m["name"]: m for m in json.loads(body)["machines"]}
                entry = machines.get("aj300-01")
                if entry is not None and entry.get("live", {}).get("printing"):
                    seen_printing = entry
                    fleet_page = get("")[1]
                    machine = json.loads(get("api/machine/aj300-01")[1])
                    break
            time.sleep(0.5)
        demo.wait(timeout=300)
    finally:
        _stop(demo)
    log = (tmp_path / "demo.log").read_text()
    assert demo.returncode == 0, log
    # the page showed the machine printing, with the twin's states, while the print ran
    assert seen_printing is not None, log
    assert seen_printing["live"]["time_s"] > 0
    assert seen_printing["status"] in ("printing", "alarm")
    assert any(np.isfinite(s["mean"]) for s in seen_printing["states"]), seen_printing
    assert b"aj300-01" in fleet_page
    assert machine["live"]["printing"] and len(machine["live"]["samples"]) >= 1
    assert f"dashboard: open {base}" in log
    summary = json.loads((tmp_path / "out" / "live_summary.json").read_text())
    assert summary["dashboard_url"] == base
    assert summary["alarm"]["cause"] == "nozzle_clog"
    assert 0 <= summary["delay_s"] <= 60
    assert any(e["state"] == "raised" for e in summary["events_received_by_second_client"])
    # without --keep-open the dashboard stopped with the demo
    with socket.socket() as s:
        s.settimeout(2)
        assert s.connect_ex(("127.0.0.1", port)) != 0
