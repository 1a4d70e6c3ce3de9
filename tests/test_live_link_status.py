"""The machine link's state on the live engine's publish path (an operator-visible
status when the OPC UA server goes away), in process on loopback, every wait bounded.
"""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

asyncua = pytest.importorskip("asyncua")

from ajtwin.engine.fleet import LiveEngine  # noqa: E402
from ajtwin.engine.messages import LinkMessage, LinkState  # noqa: E402
from ajtwin.live.link import OpcUaLink, OpcUaLogin  # noqa: E402
from ajtwin.web.pages import fleet_rows  # noqa: E402
from ajtwin.web.publisher import LivePublisher  # noqa: E402

#: the twin waits for this many samples before its first step: no JAX compile in these tests
NO_STEPS = {"initial_samples": 100_000}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _links(messages, machine="m1"):
    return [m["link"] for m in messages if m.get("machine") == machine and "link" in m]


def test_unreachable_server_is_published_as_reconnecting_with_attempts():
    """Nothing listens on the port: connecting, then reconnecting attempt 1, 2, 3 … with
    the time the link was lost, the reason and the back-off (0.5 s, then 1 s: within a
    second at first); 'ended' when stopped."""
    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    engine = LiveEngine(twin_overrides=NO_STEPS)
    publisher = LivePublisher()
    messages: list[dict] = []
    engine.subscribe(lambda m: messages.append(m.to_dict()))
    engine.subscribe(publisher.publish_engine)
    link = OpcUaLink(url, ["m1", "m2"], engine, max_backoff_s=1.5, login=OpcUaLogin(timeout_s=2.0))

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(link.run(stop))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (link.link.attempt if link.link else 0) < 3:
            await asyncio.sleep(0.05)
        stop.set()
        await asyncio.wait_for(task, 15)

    t0 = time.time()
    asyncio.run(main())
    engine.shutdown()
    links = _links(messages)
    assert _links(messages, "m2") == links  # every followed machine hears the same
    states = [x["state"] for x in links]
    assert states[0] == "connecting" and states[-1] == "ended"
    lost = [x for x in links if x["state"] == "reconnecting"]
    assert [x["attempt"] for x in lost][:3] == [1, 2, 3]
    # one outage: the same 'since' (when it was first lost); retries within a second at first
    assert len({x["since"] for x in lost}) == 1 and t0 <= lost[0]["since"] <= time.time()
    assert [x["retry_in_s"] for x in lost[:3]] == [0.5, 1.0, 1.0]
    assert all(x["url"] == url and x["reason"] for x in lost)
    assert not any("step" in m for m in messages)  # no twin steps without a server
    assert link.reconnects >= 3

    # the dashboard's side: the publisher keeps the last state and renders it
    shown = publisher.link("m1")
    assert shown["state"] == "ended" and shown["text"] == "link closed (prints finished)"
    publisher.publish_engine(LinkMessage("m1", LinkState(**lost[2])))
    text = publisher.link("m1")["text"]
    since = time.strftime("%H:%M:%S UTC", time.gmtime(lost[2]["since"]))
    # ... with why, in words
    reason = lost[2]["reason"]
    assert reason.startswith(f"nothing listens at {url} (connection refused)")
    assert text.startswith(f"link lost since {since} ({reason}) — reconnecting (attempt 3")
    assert publisher.latest("m1") is None  # a link state is not a sample
    row = fleet_rows(
        [{"name": "m1", "status": "idle", "link": publisher.link("m1"), "states": None}]
    )
    assert 'class="link reconnecting"' in row and "reconnecting (attempt 3" in row


def test_server_gone_and_back_reconnected_with_gap_and_health_linkstatus():
    """A served machine: connected; the server stops → reconnecting since the loss; it comes
    back on the same port → connected with the gap, and Health/LinkStatus says so."""
    from asyncua import Client, ua

    from ajtwin.live.printer_server import PrinterServer, VirtualMachine

    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    machine = VirtualMachine("m1", "exp1", seed=1, speed=1.0, duration_min=2)
    engine = LiveEngine(twin_overrides=NO_STEPS)
    messages: list[dict] = []
    engine.subscribe(lambda m: messages.append(m.to_dict()))
    link = OpcUaLink(url, ["m1"], engine, max_backoff_s=0.3, login=OpcUaLogin(timeout_s=2.0))

    async def wait_for(predicate, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return
            await asyncio.sleep(0.05)
        raise AssertionError(f"timed out after {timeout_s} s waiting for {what}: {messages}")

    def states():
        return [x["state"] for x in _links(messages)]

    async def serve():
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(PrinterServer(url, [machine]).serve(stop, ready.set))
        await asyncio.wait_for(ready.wait(), 60)
        return stop, task

    async def main():
        server_stop, server = await serve()
        link_stop = asyncio.Event()
        follow = asyncio.create_task(link.run(link_stop))
        try:
            await wait_for(lambda: "connected" in states(), 30, "the first connection")
            t_gone = time.time()
            server_stop.set()
            await asyncio.wait_for(server, 30)
            await wait_for(
                lambda: (link.link.attempt if link.link else 0) >= 2, 30, "two failed attempts"
            )
            server_stop, server = await serve()
            await wait_for(lambda: states().count("connected") >= 2, 30, "the reconnection")
            async with Client(url, timeout=4) as client:
                idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                node = client.get_node(ua.NodeId("m1/Monitoring/Health/LinkStatus", idx))
                health = await node.read_value()
            return t_gone, time.time(), health
        finally:
            link_stop.set()
            await asyncio.wait_for(follow, 30)
            server_stop.set()
            await asyncio.wait_for(server, 30)

    t_gone, t_back, health = asyncio.run(main())
    engine.shutdown()
    links = _links(messages)
    order = [x["state"] for x in links]
    first = order.index("connected")
    back = len(order) - 1 - order[::-1].index("connected")
    lost = [x for x in links[first:back] if x["state"] == "reconnecting"]
    assert lost and [x["attempt"] for x in lost] == list(range(1, len(lost) + 1))
    assert len({x["since"] for x in lost}) == 1 and t_gone <= lost[0]["since"] <= t_back
    assert links[first]["gap_s"] is None  # the first connection had no outage
    gap = links[back]["gap_s"]
    assert 0 < gap <= t_back - t_gone + 0.5 and links[back]["attempt"] == 0
    assert health.startswith("connected ") and f"back after a {gap:.0f} s gap" in health
    assert f"({len(lost)} failed attempt(s))" in health
    assert order[-1] == "ended"
