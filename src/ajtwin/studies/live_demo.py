"""``ajtwin demo --live``: a virtual printer served over OPC UA, the live twin beside it.

Starts ``ajtwin printer serve`` (nozzle clog at 4 min, ×30) as a child process on a free
loopback port, follows it with the live twin in this process (registry in the demo
folder), listens for the twin's alarm events as a second OPC UA client, and stops the
server by its PID. About a minute on a laptop.

The browser dashboard (``ajtwin.web``) is served from this same process on 127.0.0.1
while the print runs: every engine message is pushed to its pages, as with
``ajtwin live ... --dashboard``. Its address is echoed before the print starts.
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

from asyncua import Client, ua

from ajtwin.engine.fleet import LiveEngine
from ajtwin.engine.messages import StepMessage
from ajtwin.live.link import OpcUaLink
from ajtwin.store.registry import Registry
from ajtwin.web.publisher import LivePublisher
from ajtwin.web.server import BackgroundServer

ONSET_MIN = 4.0
DURATION_MIN = 7.0
SPEED = 30.0
MACHINE = "aj300-01"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_live_demo(
    out_dir, seed: int = 0, echo=print, dashboard_port: int | None = 0, after=None
) -> dict:
    """Serve, follow, alarm; returns a summary dict (also written to live_summary.json).

    Parameters
    ----------
    out_dir : demo folder (registry, server log, summary)
    seed : seed of the virtual print
    echo : callable(str), progress lines
    dashboard_port : int or None
        Serve the dashboard on 127.0.0.1:PORT from this process (0: a free port; None: no
        dashboard). Its address is echoed before the print starts and is the summary's
        ``dashboard_url``.
    after : callable(summary), optional
        Called once the print has ended and the summary is written, while the dashboard
        still serves (``ajtwin demo --live --keep-open`` waits in it for Ctrl-C).
    """

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "live-registry.sqlite"
    for suffix in ("", "-wal", "-shm"):
        Path(str(store) + suffix).unlink(missing_ok=True)
    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    registry = Registry(store)
    engine = LiveEngine(registry)
    dashboard = publisher = None
    try:
        if dashboard_port is not None:
            # before the printer starts, so a person can open the page for the whole print

            publisher = LivePublisher()
            engine.subscribe(publisher.publish_engine)
            publisher.open_print(MACHINE)
            dashboard = BackgroundServer(registry.path, publisher, port=dashboard_port)
            echo(f"      dashboard: open {dashboard.url} to watch the print live")
        engine.warm_up()
        summary = _serve_and_follow(out, url, seed, engine, echo)
        engine.shutdown()  # everything committed is in the registry before the pages read it
        if publisher is not None:
            publisher.end_print(MACHINE)
        summary["registry"] = str(store)
        summary["dashboard_url"] = None if dashboard is None else dashboard.url
        (out / "live_summary.json").write_text(json.dumps(summary, indent=2, default=str))
        if after is not None:
            after(summary)
    finally:
        engine.shutdown()
        registry.close()
        if dashboard is not None:
            dashboard.stop()
    return summary


def _serve_and_follow(out: Path, url: str, seed: int, engine, echo) -> dict:
    """The printer server child, the live link and a second (event) client; the summary."""

    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    server_log = (out / "live-server.log").open("w")
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ajtwin.cli",
            "printer",
            "serve",
            "--scenario",
            "nozzle_clog",
            "--seed",
            str(seed),
            "--speed",
            str(SPEED),
            "--duration-min",
            str(DURATION_MIN),
            "--fault-onset-min",
            str(ONSET_MIN),
            "--endpoint",
            url,
        ],
        stdout=server_log,
        stderr=subprocess.STDOUT,
        env=env,
    )
    echo(
        f"      virtual printer {MACHINE} served at {url} (pid {server.pid}), x{SPEED:g}, "
        f"nozzle clog from {ONSET_MIN:g} min"
    )
    received: list = []
    raised: list = []
    engine.subscribe(lambda m: raised.extend(m.raised()) if isinstance(m, StepMessage) else None)
    t0 = time.monotonic()

    async def listen(done: asyncio.Event):

        while not done.is_set():
            try:
                async with Client(url, timeout=4) as client:
                    idx = await client.get_namespace_index("urn:ajtwin:aerosol-jet")
                    etype = await client.nodes.base_event_type.get_child(
                        f"{idx}:TwinAlarmEventType"
                    )

                    class Handler:
                        def event_notification(self, event):
                            received.append(
                                {
                                    "machine": event.Machine,
                                    "cause": event.Cause,
                                    "state": event.AlarmState,
                                    "detected_s": event.DetectedTime,
                                }
                            )

                    sub = await client.create_subscription(50, Handler())
                    await sub.subscribe_events(client.nodes.server, etype)
                    while not done.is_set():
                        await asyncio.sleep(0.2)
                    await asyncio.sleep(1.0)
                    return
            except (OSError, TimeoutError, ua.UaError):
                await asyncio.sleep(0.5)

    async def main():
        done = asyncio.Event()
        listener = asyncio.create_task(listen(done))
        link = OpcUaLink(url, [MACHINE], engine, max_backoff_s=1.0)
        try:
            await asyncio.wait_for(link.run(), timeout=300)
        finally:
            done.set()
            await asyncio.wait_for(listener, 30)
        return link

    try:
        link = asyncio.run(main())
    finally:
        if server.poll() is None:
            os.kill(server.pid, signal.SIGTERM)
            try:
                server.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.kill(server.pid, signal.SIGKILL)
                server.wait(timeout=20)
        server_log.close()
    onset_s = ONSET_MIN * 60
    first = next((e for e in raised if e["detected_s"] >= onset_s), None)
    return {
        "endpoint": url,
        "onset_s": onset_s,
        "alarm": first,
        "delay_s": None if first is None else first["detected_s"] - onset_s,
        "false_alarms": sum(e["detected_s"] < onset_s for e in raised),
        "events_received_by_second_client": received,
        "reconnects": link.reconnects,
        "wall_s": time.monotonic() - t0,
    }
