"""A scripted OPC UA machine for the live link's tests: the address space of
``ajtwin printer serve`` (docs/reference/opcua.md) with a misbehaviour to order.

    python tests/opcua_machine.py MODE PORT [ROWS]

MODE: ``back`` (exp1 seed 1, samples 100-129 stamped going backwards, 100 - 3 s each),
``statebad`` (PrintState set to the number 3.14 once), ``burst`` (ROWS rows written in one
SampleBuffer value, then ``finished``), ``restart`` (ROWS samples, then the server stops —
its clients get BadShutdown — and starts again 1.5 s later with a new print from t = 0, of
ROWS + 60 samples, then ``finished``; no PrintId: the clock alone tells), ``newid`` (PrintId
``p1``, ROWS samples, then PrintId ``p2`` and a new print of 60 samples from t = 0: with ROWS
< 60 the clock goes back too little to tell, the PrintId alone does), ``late`` (a print that
began 200 s before the client subscribed: its samples from t = 200 s), ``silent`` (a TCP
socket that accepts and never answers). Prints ``up`` when it listens; stopped by its PID.
"""

from __future__ import annotations

import asyncio
import socket
import sys

import numpy as np
from asyncua import Server, ua

from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS
from ajtwin.live.opcua import HEALTH_STATES, NAMESPACE_URI, node_path
from ajtwin.simulation import simulate

BUFFER_ROWS = 300


def rows_of(n: int) -> np.ndarray:
    """n rows of t, I_A, Q_c, Q_s and the five outputs: exp1 seed 1, repeated, t = 0 … n − 1."""
    record = simulate("exp1", seed=1, duration_min=min(n, 600) / 60.0)
    base = np.column_stack([record.inputs, record.outputs])
    rows = np.column_stack([np.arange(n, dtype=float), base[np.arange(n) % len(base)]])
    assert rows.shape[1] == 1 + len(INPUT_COLUMNS) + len(OUTPUT_COLUMNS)
    return rows


async def silent(port: int) -> None:
    """Accept connections and never answer (a hung server, a wrong service on the port)."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(8)
    srv.setblocking(False)
    print("up", flush=True)
    held = []
    loop = asyncio.get_running_loop()
    while True:
        conn, _ = await loop.sock_accept(srv)
        held.append(conn)


#: where the print began before the ``late`` machine's first sample [s]
LATE_S = 200.0


async def _server(port: int, name: str, print_id: str | None = None):
    """The machine's server (not started) and its PrintState and SampleBuffer nodes, and
    its PrintId node when ``print_id`` is given (else None: a machine without one)."""
    server = Server()
    await server.init()
    # a machine whose PrintState changes type, as a misconfigured PLC's may: let it
    server.iserver.aspace._is_expected_variant_type = lambda *args, **kwargs: True
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}")
    idx = await server.register_namespace(NAMESPACE_URI)
    folder = await server.nodes.objects.add_folder(ua.NodeId("Machines", idx), f"{idx}:Machines")

    def nid(*parts):
        return ua.NodeId(node_path(name, *parts), idx)

    obj = await folder.add_object(nid(), f"{idx}:{name}")
    monitoring = await obj.add_object(nid("Monitoring"), f"{idx}:Monitoring")
    process = await monitoring.add_object(nid("Monitoring", "Process"), f"{idx}:Process")
    health = await monitoring.add_object(nid("Monitoring", "Health"), f"{idx}:Health")
    any_type = ua.NodeId(ua.ObjectIds.BaseDataType)
    state = await process.add_variable(
        nid("Monitoring", "Process", "PrintState"), f"{idx}:PrintState", "printing",
        datatype=any_type,
    )  # fmt: skip
    ident = None
    if print_id is not None:
        ident = await process.add_variable(
            nid("Monitoring", "Process", "PrintId"), f"{idx}:PrintId", print_id
        )
    empty = [float("nan")] * (BUFFER_ROWS * 9)
    buffer = await process.add_variable(
        nid("Monitoring", "Process", "SampleBuffer"),
        f"{idx}:SampleBuffer",
        ua.Variant(empty, ua.VariantType.Double),
    )
    for key in HEALTH_STATES:
        for suffix in ("", "Std"):
            var = await health.add_variable(
                nid("Monitoring", "Health", key + suffix), f"{idx}:{key}{suffix}", float("nan")
            )
            await var.set_writable()
    defaults = {"Status": "", "Cause": "", "Alarm": "", "TwinTime": -1.0, "NIS": float("nan"),
                "Theta": [0.0] * 5, "LinkStatus": ""}  # fmt: skip
    for key, value in defaults.items():
        var = await health.add_variable(nid("Monitoring", "Health", key), f"{idx}:{key}", value)
        await var.set_writable()
    return server, state, buffer, ident


async def machine(mode: str, port: int, n_rows: int, name: str = "m1") -> None:
    """Serve machine ``name`` and play ``mode`` (module docstring)."""
    server, state, buffer, ident = await _server(port, name, "p1" if mode == "newid" else None)
    rows = rows_of(n_rows if mode not in ("restart", "newid") else n_rows + 60)
    if mode == "late":
        rows[:, 0] += LATE_S
    async with server:
        print("up", flush=True)
        await asyncio.sleep(2.0)  # the client subscribes
        if mode == "burst":
            await buffer.write_value(ua.Variant(rows.ravel().tolist(), ua.VariantType.Double))
            await asyncio.sleep(1.0)
        elif mode == "newid":
            await _play(mode, rows[:n_rows], buffer, state, server)
            await ident.write_value(ua.Variant("p2", ua.VariantType.String))
            await asyncio.sleep(0.5)  # the new id is published before the new print's samples
            await _play(mode, rows[:60], buffer, state, server)
        else:
            await _play(mode, rows[:n_rows] if mode == "restart" else rows, buffer, state, server)
        if mode != "restart":
            await state.write_value(ua.Variant("finished", ua.VariantType.String))
            await asyncio.sleep(3600)  # until stopped
    # restart: the server was stopped mid-print; it comes back and prints again from t = 0
    await asyncio.sleep(1.5)
    server, state, buffer, _ = await _server(port, name)
    async with server:
        await asyncio.sleep(2.0)  # the client reconnects
        await _play(mode, rows, buffer, state, server)
        await state.write_value(ua.Variant("finished", ua.VariantType.String))
        await asyncio.sleep(3600)


async def _play(mode, rows, buffer, state, server) -> None:
    """Publish the rows one at a time (40 a second) in a rolling buffer."""
    shown = []
    for k, row in enumerate(rows):
        row = row.copy()
        if mode == "back" and 100 <= k < 130:
            row[0] = 100.0 - (k - 100) * 3.0  # the machine's clock going back
        shown = (shown + [row])[-BUFFER_ROWS:]
        table = np.full((BUFFER_ROWS, 9), np.nan)
        table[-len(shown) :] = shown
        await buffer.write_value(ua.Variant(table.ravel().tolist(), ua.VariantType.Double))
        if mode == "statebad" and k == 60:
            await server.write_attribute_value(
                state.nodeid, ua.DataValue(ua.Variant(3.14, ua.VariantType.Double))
            )
        await asyncio.sleep(1.0 / 40)
    await asyncio.sleep(1.0)


if __name__ == "__main__":
    mode, port = sys.argv[1], int(sys.argv[2])
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 240
    asyncio.run(silent(port) if mode == "silent" else machine(mode, port, n))
