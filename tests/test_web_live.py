"""The dashboard fed by the real live engine (ajtwin.live): messages → samples → pages."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.live.engine import LiveEngine, Sample
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
    engine.subscribe(messages.append)
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


def test_live_command_serves_the_dashboard(clog_record, tmp_path):
    from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS
    from ajtwin.live.cli import live

    rec = clog_record.window(0, 60)
    columns = ["time_s", *INPUT_COLUMNS, *OUTPUT_COLUMNS]
    rows = rec.data[columns].to_numpy(float)
    path = tmp_path / "print.csv"
    lines = [",".join(columns)] + [",".join(repr(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    store = tmp_path / "r.sqlite"
    args = ["--machine", "m1", "--follow", str(path), "--idle-timeout", "2",
            "--store", str(store), "--dashboard", "0"]  # fmt: skip
    result = CliRunner().invoke(live, args)
    assert result.exit_code == 0, result.output
    line = next(x for x in result.output.splitlines() if x.startswith("dashboard: open "))
    port = int(line.rsplit(":", 1)[1].strip("/ "))
    assert "print stored as registry print id" in result.output
    # the server was stopped with the command: its port no longer answers
    with socket.socket() as s:
        s.settimeout(2)
        assert s.connect_ex(("127.0.0.1", port)) != 0
