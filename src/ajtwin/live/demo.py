"""``ajtwin demo --live``: a virtual printer served over OPC UA, the live twin beside it.

Starts ``ajtwin printer serve`` (nozzle clog at 4 min, ×30) as a child process on a free
loopback port, follows it with the live twin in this process (registry in the demo
folder), listens for the twin's alarm events as a second OPC UA client, and stops the
server by its PID. About a minute on a laptop.
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

ONSET_MIN = 4.0
DURATION_MIN = 7.0
SPEED = 30.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_live_demo(out_dir, seed: int = 0, echo=print) -> dict:
    """Serve, follow, alarm; returns a summary dict (also written to live_summary.json)."""
    from ajtwin.live.engine import LiveEngine
    from ajtwin.live.link import OpcUaLink
    from ajtwin.store.registry import Registry

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "live-registry.sqlite"
    for suffix in ("", "-wal", "-shm"):
        Path(str(store) + suffix).unlink(missing_ok=True)
    url = f"opc.tcp://127.0.0.1:{_free_port()}"
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
        f"      virtual printer aj300-01 served at {url} (pid {server.pid}), x{SPEED:g}, "
        f"nozzle clog from {ONSET_MIN:g} min"
    )
    registry = Registry(store)
    engine = LiveEngine(registry)
    engine.warm_up()
    received: list = []
    raised: list = []
    engine.subscribe(
        lambda m: raised.extend(e for e in m.get("events", []) if e.get("state") == "raised")
    )
    t0 = time.monotonic()

    async def listen(done: asyncio.Event):
        from asyncua import Client, ua

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
        link = OpcUaLink(url, ["aj300-01"], engine, max_backoff_s=1.0)
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
        server_log.close()
        engine.shutdown()
    onset_s = ONSET_MIN * 60
    first = next((e for e in raised if e["detected_s"] >= onset_s), None)
    summary = {
        "endpoint": url,
        "onset_s": onset_s,
        "alarm": first,
        "delay_s": None if first is None else first["detected_s"] - onset_s,
        "false_alarms": sum(e["detected_s"] < onset_s for e in raised),
        "events_received_by_second_client": received,
        "reconnects": link.reconnects,
        "wall_s": time.monotonic() - t0,
        "registry": str(store),
    }
    (out / "live_summary.json").write_text(json.dumps(summary, indent=2, default=str))
    registry.close()
    return summary
