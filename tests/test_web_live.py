"""The dashboard fed by the real live engine (ajtwin.live): messages → samples → pages."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.engine.fleet import LiveEngine
from ajtwin.estimation.samples import Sample
from ajtwin.model import STATE_NAMES
from ajtwin.simulation import simulate
from ajtwin.web.publisher import LivePublisher


@pytest.fixture(scope="module")
def clog_record():
    # a fast clog (as in tests/test_live.py) so a 6-min print raises the alarm early
    return simulate(
        "nozzle_clog",
        seed=5,
        duration_min=6.0,
        overrides={"fault": {"onset_min": 3.0, "nozzle_deposition_multiplier": 400.0}},
    )


def test_engine_messages_reach_the_publisher(clog_record):
    engine = LiveEngine(None, asynchronous=False)
    publisher = LivePublisher()
    messages = []
    engine.subscribe(lambda m: messages.append(m.to_dict()))
    engine.subscribe(publisher.publish_engine)
    for t, u, y in zip(clog_record.time_s, clog_record.inputs, clog_record.outputs):
        engine.feed("aj1", Sample(t, u, y))
    engine.shutdown()
    committed = [m for m in messages if not m["provisional"]]
    samples = publisher.snapshot("aj1")
    assert len(samples) == len(committed) > 300
    # the states a page draws are the engine's, in the project's state order
    k = len(samples) // 2
    assert samples[k]["time_s"] == committed[k]["time_s"]
    assert samples[k]["states"] == [committed[k]["states"][n] for n in STATE_NAMES]
    assert samples[k]["detectors"]["cusum"][5] == committed[k]["cusum"]["P_c+P_s"]
    # the engine's clog alarm is on the publisher, after the true onset
    alarms = publisher.alarms("aj1")
    assert alarms and alarms[0]["cause"] == "nozzle_clog"
    assert 180.0 <= alarms[0]["detected_s"] < 300.0
    raised = [ev for m in committed for ev in m["events"] if ev["state"] == "raised"]
    assert [a["detected_s"] for a in alarms] == [ev["detected_s"] for ev in raised]
    assert np.isfinite(samples[-1]["detectors"]["window_nis_log10p"])


def test_live_command_serves_the_dashboard_after_the_print_until_stopped(
    clog_record, tmp_path, monkeypatch
):
    """A followed print that ends leaves its page served (the operator is still looking at
    it) until Ctrl-C; the server goes with the command."""
    import ajtwin.cli.live as live_cli
    from ajtwin.cli.live import live
    from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS

    rec = clog_record.window(0, 60)
    columns = ["time_s", *INPUT_COLUMNS, *OUTPUT_COLUMNS]
    rows = rec.data[columns].to_numpy(float)
    path = tmp_path / "print.csv"
    lines = [",".join(columns)] + [",".join(repr(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    store = tmp_path / "r.sqlite"
    args = ["--machine", "m1", "--follow", str(path), "--idle-timeout", "2",
            "--store", str(store), "--dashboard", "0"]  # fmt: skip
    answered = []

    def ctrl_c():  # the wait after the print: the page still answers, then "Ctrl-C"
        import urllib.request

        server = live_cli_server[0]
        with urllib.request.urlopen(server.url + "api/fleet", timeout=10) as r:
            answered.append(r.status)
        raise KeyboardInterrupt

    live_cli_server = []
    real_serve = live_cli._serve_dashboard

    def serve(*a, **k):
        live_cli_server.append(real_serve(*a, **k))
        return live_cli_server[0]

    monkeypatch.setattr(live_cli, "_serve_dashboard", serve)
    monkeypatch.setattr(live_cli, "_wait_until_interrupted", ctrl_c)
    result = CliRunner().invoke(live, args)
    assert result.exit_code == 0, result.output
    line = next(x for x in result.output.splitlines() if x.startswith("dashboard: open "))
    port = int(line.rsplit(":", 1)[1].strip("/ "))
    assert "print stored as registry print id" in result.output
    assert answered == [200] and "dashboard still at" in result.output
    assert "stopped (the prints had ended and are stored)" in result.output
    # the server was stopped with the command: its port no longer answers
    with socket.socket() as s:
        s.settimeout(2)
        assert s.connect_ex(("127.0.0.1", port)) != 0


def test_live_demo_serves_the_dashboard_and_keeps_it_open(clog_record, tmp_path, monkeypatch):
    """``ajtwin demo --live --keep-open`` wiring, without the OPC UA part: the engine's
    samples reach the dashboard the demo serves, which answers after the print until Ctrl-C
    and is gone after it. (The whole demo over OPC UA: the slow test in test_live_opcua.)"""
    import json
    import urllib.request

    import ajtwin.cli.demo as demo_cli
    import ajtwin.studies.live_demo as live_demo
    from ajtwin.estimation.samples import Sample

    def print_without_opcua(out, url, seed, engine, echo):
        for k in range(20):
            t, u, y = clog_record.time_s[k], clog_record.inputs[k], clog_record.outputs[k]
            engine.feed(live_demo.MACHINE, Sample(t, u, y))
        seen["during_print"] = fleet(seen["url"])
        engine.close(live_demo.MACHINE)  # the print ends: stored in the registry
        return {"endpoint": url, "onset_s": 240.0, "alarm": None, "delay_s": None,
                "false_alarms": 0, "events_received_by_second_client": [], "reconnects": 0,
                "wall_s": 1.0}  # fmt: skip

    seen = {}

    def fleet(base):
        with urllib.request.urlopen(base + "api/fleet", timeout=10) as r:
            return {m["name"]: m for m in json.loads(r.read())["machines"]}

    def ctrl_c():  # the --keep-open wait: look at the page once, then "Ctrl-C"
        seen["after_print"] = fleet(seen["url"])
        raise KeyboardInterrupt

    real_run = live_demo.run_live_demo

    def run(*args, **kwargs):
        echo = kwargs.pop("echo")

        def echo_and_note(line):
            if "dashboard: open " in line:
                seen["url"] = line.split("dashboard: open ")[1].split()[0]
            echo(line)

        return real_run(*args, echo=echo_and_note, **kwargs)

    monkeypatch.setattr(live_demo, "_serve_and_follow", print_without_opcua)
    monkeypatch.setattr(live_demo, "run_live_demo", run)
    monkeypatch.setattr(demo_cli, "_wait_for_ctrl_c", ctrl_c)
    result = CliRunner().invoke(demo_cli.demo_command, ["--live", "--keep-open", "--out",
                                                        str(tmp_path)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"dashboard still at {seen['url']}; Ctrl-C stops it" in result.output
    # while printing the page shows the twin's last step and its states ...
    entry = seen["during_print"][live_demo.MACHINE]
    assert entry["live"] == {"time_s": clog_record.time_s[19], "printing": True}
    assert entry["status"] == "printing" and len(entry["states"]) >= 4
    # ... and after the print (--keep-open) the print the live twin stored
    entry = seen["after_print"][live_demo.MACHINE]
    assert entry["status"] != "printing" and entry["n_prints"] == 1
    assert json.loads((tmp_path / "live_summary.json").read_text())["dashboard_url"] == seen["url"]
    port = int(seen["url"].rsplit(":", 1)[1].strip("/"))
    with socket.socket() as s:  # stopped after Ctrl-C
        s.settimeout(2)
        assert s.connect_ex(("127.0.0.1", port)) != 0
