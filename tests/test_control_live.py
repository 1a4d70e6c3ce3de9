"""Closed-loop control of a live machine: the served virtual printer's stepping path and
``ajtwin control`` against it over OPC UA on loopback (127.0.0.1, free port, bounded waits)."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.live.opcua import SAMPLE_COLUMNS
from ajtwin.simulation import simulate


def _served(machine, stops) -> np.ndarray:
    for stop in stops:  # an irregular publishing rhythm, as the server's ticks give
        machine.rows(stop, 8)
    return machine.rows(machine.n_samples, machine.n_samples)


def test_served_print_without_writes_is_the_batch_print():
    from ajtwin.live.printer_server import VirtualMachine

    machine = VirtualMachine("m1", "exp1", seed=3, speed=30, duration_min=3)
    batch = simulate("exp1", 3, 3).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    served = _served(machine, [1, 2, 5, 9, 40, 41, 100, 170])
    assert served.shape == batch.shape == (180, len(SAMPLE_COLUMNS))
    assert np.array_equal(np.isnan(served), np.isnan(batch))
    np.testing.assert_allclose(served, batch, rtol=1e-12, atol=0.0)


def test_served_write_is_the_print_with_that_step():
    """A write at 64.3 s applies from 66 s: the batch print with that step in its schedule
    (what the server did before it stepped), the other inputs' schedule untouched."""
    from ajtwin.live.printer_server import VirtualMachine

    clog = {"fault": {"onset_min": 0.5}}
    machine = VirtualMachine("m1", "nozzle_clog", seed=2, speed=30, duration_min=3, overrides=clog)
    machine.rows(50, 8)
    assert machine.set_point("sheath_flow_sccm", 44.0, at_s=64.3) is None
    assert machine.set_point("carrier_flow_sccm", 80.0, at_s=70.0) is not None  # limits
    served = _served(machine, [70, 130])
    overrides = {"inputs": {"sheath_flow_sccm": [[0.0, 50.0], [66 / 60, 44.0]]}, **clog}
    batch = simulate("nozzle_clog", 2, 3, overrides).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    np.testing.assert_allclose(served, batch, rtol=1e-12, atol=0.0)
    assert machine.schedule == {"sheath_flow_sccm": [[66 / 60, 44.0]]}
    unchanged = simulate("nozzle_clog", 2, 3, clog).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    np.testing.assert_array_equal(served[:66], unchanged[:66])  # the past stays
    assert np.nanmean(served[70:, 3]) == pytest.approx(44.0, abs=0.2)  # reported Q_s
    assert np.nanmean(unchanged[70:, 3]) == pytest.approx(50.0, abs=0.2)


# --------------------------------------------------------------------------- #
# ajtwin control against the served virtual printer, in-process, loopback
# --------------------------------------------------------------------------- #


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_control_writes_reach_the_printer_and_steer_the_line():
    """×30 on exp1 (nominal line ~74 µm at 23/50 sccm), target 65 µm: the controller's
    writes arrive, stay inside the limits and rate limits, and the true line moves to it.

    The machine's atomizer current is limited to 365–385 mA (its registry limits and the
    server's EURange), so the flows must do the work and the limits bind. Seed 2: on seed 1
    a Q_c step of −2 sccm at 75 s makes the twin raise a false "atomizer" alarm ~2 min later
    (offline too, without the server), and the controller then holds, as it must."""
    import asyncio

    pytest.importorskip("asyncua")
    from ajtwin.apps.planning.mpc import ControlSettings
    from ajtwin.apps.planning.supervisor import ControlTarget
    from ajtwin.live.control_link import ControlLink
    from ajtwin.live.link import OpcUaLogin
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine
    from ajtwin.model.limits import DEFAULT_LIMITS

    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    settings = ControlSettings.load()
    target = 65.0
    limits = {k: list(v) for k, v in DEFAULT_LIMITS.items()}
    limits["atomizer_current_mA"] = [365.0, 385.0]

    async def main():
        link = ControlLink(
            url,
            "m1",
            ControlTarget(target, limits=limits),
            login=OpcUaLogin("operator", "pw", timeout_s=4),
        )
        link.prepare()  # compile before the served print's clock starts
        machine = VirtualMachine("m1", "exp1", seed=2, speed=30, duration_min=8, limits=limits)
        server = PrinterServer(url, [machine], users={"operator": "pw"})
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(server.serve(stop, ready.set))
        try:
            await asyncio.wait_for(ready.wait(), 60)
            await asyncio.wait_for(link.run(), 120)  # ends when the print is finished
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)
        return link, machine

    link, machine = asyncio.run(main())
    written = [d for d in link.decisions if d.written]
    assert written, [(d.time_s, d.status, d.reason) for d in link.decisions]
    # the writes arrived: the served print's schedule holds them
    schedule = machine.printer.schedule[: machine.printer.k]
    changes = np.flatnonzero(np.any(np.diff(schedule, axis=0) != 0, axis=1)) + 1
    in_print = [d for d in written if d.time_s < machine.n_samples - 10]  # later: print over
    assert len(changes) >= len(in_print) > 10
    for k in changes:  # every change of the served schedule is one of the controller's commands
        assert any(np.allclose(schedule[k], d.command, rtol=0, atol=1e-12) for d in written)
    # inside the machine's limits, every second of the print
    for i, column in enumerate(("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm")):
        low, high = limits[column]
        assert np.all((schedule[:, i] >= low) & (schedule[:, i] <= high)), column
    # the rate limits, between the decisions (print time) and between what the server applied
    rates = np.asarray(settings.rate_limits)
    commands = np.array([d.command for d in link.decisions])
    times = np.array([d.time_s for d in link.decisions])
    assert np.all(np.diff(times) >= settings.period_s - 1e-9)
    assert np.all(np.abs(np.diff(commands, axis=0)) <= rates * settings.period_s + 1e-9)
    # applied by the server a period apart (the controller waits for a period on the
    # machine's SampleTime, which lags the server's clock by up to one 0.1 s publishing
    # tick = 3 s of print at ×30) less the 1 s rounding of the applying second
    steps = np.abs(np.diff(schedule[np.r_[0, changes]], axis=0))
    gaps = np.diff(np.r_[0, changes])
    assert np.all(steps <= rates * np.minimum(gaps[:, None] + 4.0, settings.period_s) + 1e-9)
    # the true line moved toward the target
    lw = machine.true_outputs[:, 0]
    before, after = lw[:60].mean(), lw[-60:].mean()
    print(f"true L_w first minute {before:.2f} µm, last minute {after:.2f} µm")
    assert before > target + 6
    assert abs(after - target) < 0.5 * abs(before - target)


def test_control_without_login_is_refused_with_a_clear_message(tmp_path):
    """An anonymous session may not write set-points (docs/reference/opcua.md): `ajtwin control`
    stops before any control with a message that says what to give."""
    import asyncio
    import threading

    pytest.importorskip("asyncua")
    from click.testing import CliRunner

    from ajtwin.cli import main as cli
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine

    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    machine = VirtualMachine("m1", "exp1", seed=1, speed=1, duration_min=5)
    server = PrinterServer(url, [machine])  # no users: anonymous reads, no set-point writes
    ready = threading.Event()
    state = {}

    def serve():
        async def run():
            state["loop"], state["stop"] = asyncio.get_running_loop(), asyncio.Event()
            await server.serve(state["stop"], ready.set)

        asyncio.run(run())

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        assert ready.wait(60), "the server did not start"
        result = CliRunner().invoke(
            cli,
            [
                "control",
                "--machine",
                "m1",
                "--target-linewidth",
                "65",
                "--opcua",
                url,
                "--store",
                str(tmp_path / "none.sqlite"),
            ],
        )
    finally:
        if "loop" in state:
            state["loop"].call_soon_threadsafe(state["stop"].set)
        thread.join(30)
    assert not thread.is_alive()
    assert result.exit_code == 1, result.output
    assert "BadUserAccessDenied" in result.output
    assert "authenticated user" in result.output and "--username/--password" in result.output
    assert machine.schedule == {}  # nothing was written


def test_live_control_bad_targets_name_the_reachable_range():
    from ajtwin.apps.planning.mpc import TargetError
    from ajtwin.apps.planning.strategies import nominal_state
    from ajtwin.apps.planning.supervisor import ControlTarget, Supervisor
    from ajtwin.estimation import Twin
    from ajtwin.live.control_link import ControlLink

    for bad in (float("nan"), -3.0, "wide"):
        with pytest.raises(TargetError, match="target linewidth"):
            ControlLink("opc.tcp://127.0.0.1:1", "m1", ControlTarget(bad))
    mean, cov = nominal_state(Twin.default(), [375.0, 23.0, 50.0])

    class Controller:  # the twin alone: what the reachable range needs before any MPC
        twin = Twin.default()

        @staticmethod
        def state_now():
            return mean, cov

    supervisor = Supervisor(Controller(), ControlTarget(500.0).resolved())
    with pytest.raises(TargetError, match=r"reachable now: \d+\.\d–\d+\.\d µm") as info:
        supervisor.check_reachable()
    import re

    low, high = (
        float(v) for v in re.search(r"reachable now: ([\d.]+)–([\d.]+)", str(info.value)).groups()
    )
    assert low < 74.2 < high < 500  # the nominal line at 375 mA, 23/50 sccm lies inside
    supervisor = Supervisor(Controller(), ControlTarget(65.0).resolved())
    assert supervisor.check_reachable() == pytest.approx((low, high), abs=0.05)


def test_live_control_of_a_job_print_fills_the_part_map_and_stores_the_job(tmp_path):
    """`ajtwin control --machine m1 --job PROGRAM --dashboard 0` against the served virtual
    printer running that program (×10, 5 min): set-points written within the limits, the
    dashboard's live part map filled with evaluated portions, the print stored with its job."""
    import asyncio
    import json
    import urllib.request

    pytest.importorskip("asyncua")
    from ajtwin.apps.planning.mpc import ControlSettings
    from ajtwin.apps.planning.supervisor import ControlTarget
    from ajtwin.apps.quality.part_map import parse_tolerance
    from ajtwin.cli.control import _job_engine
    from ajtwin.job import SpeedSchedule
    from ajtwin.live.control_link import ControlLink
    from ajtwin.live.link import OpcUaLogin
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine
    from ajtwin.model.limits import DEFAULT_LIMITS
    from ajtwin.store.registry import Registry

    program = tmp_path / "serpentine.prg"
    lines = []
    for k in range(16):  # strokes of 20 mm back and forth, 0.2 mm apart
        x0, x1 = (0.0, 20.0) if k % 2 == 0 else (20.0, 0.0)
        lines += [f"ptp/e (X,Y),{x0},{k * 0.2}", "OUT0.0=1", f"ptp/e (X,Y),{x1},{k * 0.2}"]
        lines.append("OUT0.0=0")
    program.write_text("\n".join(lines))
    store = tmp_path / "store.sqlite"
    job = {"program": str(program), "process_speed": SpeedSchedule.parse("stroke:2,4"),
           "camera_mode": "trailing", "offset_mm": None, "tolerance": parse_tolerance("55±3"),
           "dashboard_port": 0}  # fmt: skip
    engine, dashboard, options = _job_engine("m1", job, str(store))
    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    settings = ControlSettings.load()
    limits = {k: list(v) for k, v in DEFAULT_LIMITS.items()}

    async def main():
        link = ControlLink(
            url, "m1", ControlTarget(55.0, limits=limits),
            login=OpcUaLogin("operator", "pw", timeout_s=4), engine=engine, **options,
        )  # fmt: skip
        link.prepare()  # compile before the served print's clock starts
        machine = VirtualMachine(
            "m1", "exp1", seed=2, speed=10, duration_min=5, limits=limits, job=options["job"]
        )
        server = PrinterServer(url, [machine], users={"operator": "pw"})
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(server.serve(stop, ready.set))
        try:
            await asyncio.wait_for(ready.wait(), 60)
            await asyncio.wait_for(link.run(), 180)  # ends when the print is finished
        finally:
            stop.set()
            await asyncio.wait_for(task, 30)
        return link, machine

    try:
        link, machine = asyncio.run(main())
        with urllib.request.urlopen(dashboard.url + "api/machine/m1/part/live", timeout=30) as r:
            part = json.loads(r.read())
    finally:
        engine.shutdown()
        dashboard.stop()
    written = [d for d in link.decisions if d.written]
    assert len(written) >= 5, [(d.time_s, d.status, d.reason) for d in link.decisions]
    schedule = machine.printer.schedule[: machine.printer.k]
    for i, column in enumerate(("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm")):
        low, high = limits[column]
        assert np.all((schedule[:, i] >= low) & (schedule[:, i] <= high)), column
    commands = np.array([d.command for d in link.decisions])
    steps = np.abs(np.diff(commands, axis=0))
    assert np.all(steps <= np.asarray(settings.rate_limits) * settings.period_s + 1e-9)
    # the part map on the dashboard filled in: portions of the part evaluated from the twin
    portions = part["portions"]
    assert portions is not None, part.keys()
    print(f"{len(written)} writes; part map to {max(portions['printed_to_s']):.0f} s of print")
    assert max(portions["printed_to_s"]) > 0.5 * machine.n_samples
    assert np.all(np.isfinite(portions["lw_mean_um"]))
    # the print stored with its job
    assert link.print_id is not None
    with Registry(store, create=False) as registry:
        stored = registry.print_job(link.print_id)
    assert stored is not None and stored["program"] == "serpentine.prg"


def test_printer_serve_process_speeds_go_with_a_job():
    from click.testing import CliRunner

    from ajtwin.cli import main as cli

    result = CliRunner().invoke(cli, ["printer", "serve", "--process-speed", "2,4,3"])
    assert result.exit_code == 2 and "--process-speed goes with --job" in result.output
    result = CliRunner().invoke(
        cli, ["printer", "serve", "--job", __file__, "--process-speed", "2,,4"]
    )
    assert result.exit_code != 0 and "give speeds" in result.output
