"""Dashboard without a browser: registry adapter, publisher, watcher, input checks, CLI."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.apps.detection.streaming import AnomalyEvent
from ajtwin.cli.dashboard import dashboard
from ajtwin.engine.views import MAX_POINTS, RegistryView, binned_max, decimate, json_list
from ajtwin.store.registry import NewPrint, Registry, RegistryError
from ajtwin.web.access import check_access, is_loopback
from ajtwin.web.app import InputError, parse_advise_request, parse_forecast_request
from ajtwin.web.publisher import LivePublisher
from ajtwin.web.watcher import RegistryWatcher


def hand_print(reg, name, *, seq_before, n=50, end=None, anomalies=(), tag="a"):
    """A print with hand-made arrays (no twin): means ramp linearly, σ constant."""
    t = np.arange(n, dtype=float)
    base = np.array([3.5, 1.0, 0.0, 0.02, 4.6e-7])
    slope = np.array([1e-3, -1e-4, 1e-6, 1e-3, 1e-10])
    means = base + np.outer(t, slope)
    end_mean = means[-1] if end is None else np.asarray(end, float)
    cov = np.diag([0.01, 1e-4, 1e-8, 1e-6, 1e-16])
    return reg.save_print(
        name,
        NewPrint(
            content_hash=f"{name}-{tag}",
            source="hand-made",
            meta={"scenario": "hand"},
            summary={"mean_nis": 5.0},
            n_samples=n,
            duration_s=float(n),
            start_mean=means[0],
            start_cov=cov,
            end_mean=end_mean,
            end_cov=cov,
            theta_before=np.zeros(5),
            theta_after=np.full(5, 1e-6),
            arrays={"time_s": t, "means": means, "stds": np.tile(np.sqrt(np.diag(cov)), (n, 1))},
            anomalies=list(anomalies),
        ),
        expected_last_seq=seq_before,
    )


@pytest.fixture
def store(tmp_path):
    path = tmp_path / "r.sqlite"
    reg = Registry(path)
    for name in ("alpha", "beta", "gamma"):
        reg.add_machine(name)
    hand_print(reg, "alpha", seq_before=None)
    clog = AnomalyEvent(40.0, 31.0, "nozzle_clog", "nozzle clog (both pressures rising)", ["x"])
    hand_print(reg, "beta", seq_before=None, tag="1")
    hand_print(reg, "beta", seq_before=1, anomalies=[clog], tag="2", end=[3.9, 0.9, 0, 0.3, 4e-7])
    reg.close()
    return path


def test_fleet_summaries_from_registry(store):
    view = RegistryView(store)
    fleet = {m["name"]: m for m in view.fleet()}
    assert sorted(fleet) == ["alpha", "beta", "gamma"]
    assert fleet["gamma"]["status"] == "idle" and fleet["gamma"]["last_print"] is None
    assert fleet["alpha"]["status"] == "idle" and fleet["alpha"]["alarm"] is None
    beta = fleet["beta"]
    assert beta["status"] == "alarm" and beta["last_print"]["seq"] == 2
    assert beta["alarm"]["cause"] == "nozzle_clog" and beta["alarm"]["detected_s"] == 40
    assert beta["other_alarms"] == []
    # key states in the order d_a, φ_A, ΔR_N, V_l: the end state written above, 2σ from cov
    assert [s["symbol"] for s in beta["states"]] == ["d_a", "φ_A", "ΔR_N", "V_l"]
    assert [s["mean"] for s in beta["states"]] == [3.9, 4e-7, 0.3, 0.9]
    assert beta["states"][0]["std"] == pytest.approx(0.1)
    # the trend is the last print's estimate, decimated: first and last samples kept
    trend = fleet["alpha"]["states"][2]["trend"]
    assert trend["t"][0] == 0 and trend["t"][-1] == 49
    assert trend["v"][-1] == pytest.approx(0.02 + 49e-3)


def test_machine_detail_and_missing(store):
    view = RegistryView(store)
    m = view.machine("beta")
    assert [p["seq"] for p in m["prints"]] == [1, 2]
    assert m["prints"][1]["anomalies"] == 1 and m["prints"][0]["mean_nis"] == 5.0
    assert m["alarms"][0]["description"].startswith("nozzle clog")
    assert m["last"]["theta"] == [1e-6] * 5
    with pytest.raises(RegistryError, match="no machine 'nope'"):
        view.machine("nope")
    with pytest.raises(RegistryError, match="no registry at"):
        RegistryView(store.parent / "missing.sqlite")


def _fake_commissioning(offset_um: float):
    """What save_calibration stores, by hand (no fit): L_w offset ± 0.5 µm, rest nominal."""
    from types import SimpleNamespace

    from ajtwin.model.calibration import CALIBRATION_NAMES, Calibration

    std = {k: 0.01 for k in CALIBRATION_NAMES} | {"linewidth_offset_um": 0.5}
    determined = {k: True for k in CALIBRATION_NAMES} | {"sheath_line_factor": False}
    return SimpleNamespace(
        calibration=Calibration(linewidth_offset_um=offset_um),
        std=std,
        prior_std=std,
        determined=determined,
        priors={},
        notes=[],
        end_state=np.array([3.5, 0.9, 0.0, 0.0, 4.6e-7]),
        end_state_cov=np.diag([0.01, 1e-4, 1e-8, 1e-6, 1e-16]),
        calibration_cov=np.diag([v**2 for v in std.values()]),
        noise_factors=None,
    )


def test_fleet_and_machine_show_calibration_maintenance_and_mismatch(store):
    from ajtwin.apps.detection.mismatch import MismatchStatus
    from ajtwin.store.calibration import record_maintenance, save_calibration
    from ajtwin.web.pages import fleet_rows

    reg = Registry(store)
    save_calibration(reg, "alpha", _fake_commissioning(-3.0), "old.parquet")
    cal_id = save_calibration(reg, "alpha", _fake_commissioning(-7.25), "commission.parquet")
    record_maintenance(reg, "alpha", nozzle_cleaned=True, vial_refilled_ml=1.1)
    guard = MismatchStatus(
        True,
        130.0,
        outputs=["carrier_pressure_Pa"],
        reasons=["carrier_pressure_Pa persistently above the model"],
        fixes=["commission the machine"],
        message="model–machine mismatch: carrier_pressure_Pa persistently above the model",
    )
    # gamma's first print: the guard fired (the summary entry live/engine.py writes)
    t = np.arange(5.0)
    reg.save_print("gamma", NewPrint(
        content_hash="g1", source="hand-made", meta={}, n_samples=5, duration_s=5.0,
        summary={"mean_nis": 1.0, "mismatch": guard.to_dict()},
        start_mean=np.array([3.5, 1, 0, 0, 4.6e-7]), start_cov=np.eye(5) * 1e-4,
        end_mean=np.array([3.5, 1, 0, 0, 4.6e-7]), end_cov=np.eye(5) * 1e-4,
        theta_before=np.zeros(5), theta_after=np.zeros(5),
        arrays={"time_s": t, "means": np.zeros((5, 5)), "stds": np.ones((5, 5))}, anomalies=[],
    ), expected_last_seq=None)  # fmt: skip
    reg.close()

    view = RegistryView(store)
    fleet = {m["name"]: m for m in view.fleet()}
    alpha, gamma = fleet["alpha"], fleet["gamma"]
    assert gamma["status"] == "mismatch"
    assert gamma["mismatch"]["outputs"] == ["carrier_pressure_Pa"]
    assert gamma["mismatch"]["seq"] == 1 and gamma["model_fit"] == {"seq": 1, "ok": False}
    assert alpha["status"] == "idle" and "mismatch" not in alpha and "model_fit" not in alpha
    assert "commissioned_at" not in gamma and "last_maintenance_at" not in gamma
    assert alpha["commissioned_at"] == alpha["calibration"]["created_at"]
    assert alpha["last_maintenance"] == "nozzle cleaned, vial refilled to 1.1 mL"
    # beta's alarm outranks nothing here; its prints have no guard entry (older ingest)
    assert fleet["beta"]["status"] == "alarm" and "model_fit" not in fleet["beta"]

    html = fleet_rows(list(fleet.values()))
    gamma_row = next(r for r in html.split("<tr") if 'data-machine="gamma"' in r)
    assert "model–machine mismatch" in gamma_row and "(carrier pressure)" in gamma_row
    assert "(print #1)" in gamma_row
    alpha_row = next(r for r in html.split("<tr") if 'data-machine="alpha"' in r)
    assert "last commissioned" in alpha_row and "last maintained" in alpha_row

    m = view.machine("alpha")
    cal = m["calibration"]
    assert cal["id"] == cal_id and cal["source"] == "commission.parquet"  # the newest
    params = {p["name"]: p for p in cal["parameters"]}
    assert params["linewidth_offset_um"] == {
        "name": "linewidth_offset_um", "value": -7.25, "std_error": 0.5, "determined": True,
    }  # fmt: skip
    assert params["linewidth_gain"]["value"] == 1.0
    assert params["sheath_line_factor"]["determined"] is False
    g = view.machine("gamma")
    assert g["mismatch"]["message"] == guard.message and "calibration" not in g


def test_decimation_keeps_peaks():
    idx = decimate(10_000)
    assert len(idx) <= MAX_POINTS and idx[0] == 0 and idx[-1] == 9_999
    values = np.zeros(10_000)
    values[1235] = 7.0  # a one-sample CUSUM peak between kept samples
    assert 1235 not in idx
    assert binned_max(values, idx).max() == 7.0
    assert json_list([1.0, np.nan, np.inf]) == [1.0, None, None]


def test_publisher_fans_out_across_threads():
    pub = LivePublisher(history=5)

    async def main():
        a, b = pub.subscribe(), pub.subscribe()

        def produce():
            for k in range(8):
                sample = {"machine": "vm", "time_s": float(k), "nis": np.nan, "states": np.ones(5)}
                pub.publish(sample)

        thread = threading.Thread(target=produce)
        thread.start()
        got_a = [await asyncio.wait_for(a.get(), 5) for _ in range(8)]
        got_b = [await asyncio.wait_for(b.get(), 5) for _ in range(8)]
        thread.join(5)
        pub.unsubscribe(a)
        pub.unsubscribe(b)
        return got_a, got_b

    got_a, got_b = asyncio.run(main())
    assert (
        [e["time_s"] for e in got_a] == [float(k) for k in range(8)] == [e["time_s"] for e in got_b]
    )
    assert got_a[0]["nis"] is None and got_a[0]["states"] == [1.0] * 5  # JSON-safe
    assert all(e["type"] == "sample" and e["published_at"] > 0 for e in got_a)
    assert [s["time_s"] for s in pub.snapshot("vm")] == [3.0, 4.0, 5.0, 6.0, 7.0]
    assert pub.is_printing("vm") and pub.n_subscribers == 0
    with pytest.raises(ValueError, match="machine"):
        pub.publish({"time_s": 1.0})


def test_slow_subscriber_is_bounded():
    pub = LivePublisher()

    async def main():
        sub = pub.subscribe()
        sub.queue = asyncio.Queue(maxsize=3)
        for k in range(10):
            pub.publish({"machine": "vm", "time_s": float(k)})
        await asyncio.sleep(0.05)  # let call_soon_threadsafe callbacks run
        return [(await sub.get())["time_s"] for _ in range(3)], sub.dropped

    kept, dropped = asyncio.run(main())
    assert kept == [7.0, 8.0, 9.0] and dropped == 7


def test_live_alarm_and_new_print_after_end():
    pub = LivePublisher()
    alarm = {"detected_s": 3.0, "onset_s": 1.0, "cause": "nozzle_clog", "description": "d"}
    pub.publish({"machine": "vm", "time_s": 3.0, "alarms": [alarm]})
    assert pub.alarms("vm") == [alarm]
    pub.end_print("vm")
    assert not pub.is_printing("vm")
    pub.publish({"machine": "vm", "time_s": 0.0})  # the next print starts clean
    assert pub.alarms("vm") == [] and len(pub.snapshot("vm")) == 1


def test_watcher_sees_commits_of_another_connection(store):
    view = RegistryView(store)
    pub = LivePublisher()
    watcher = RegistryWatcher(view, pub, poll_s=0.1)
    assert watcher.check() == []
    other = Registry(store)  # another connection, like `ajtwin ingest` in another process
    pid = hand_print(other, "alpha", seq_before=1, tag="2")
    events = watcher.check()
    assert events == [
        {"type": "print", "print_id": pid, "seq": 2, "machine": "alpha", "duration_s": 50.0,
         "anomalies": 0}
    ]  # fmt: skip
    assert watcher.check() == []
    other.add_machine("delta")
    assert watcher.check() == [{"type": "machines"}]
    other.close()


LIMITS = {
    "atomizer_current_mA": [300.0, 440.0],
    "carrier_flow_sccm": [15.0, 35.0],
    "sheath_flow_sccm": [30.0, 80.0],
}


def test_forecast_request_schedule():
    body = {
        "changes": [{"input": "Q_c", "value": "26", "at": "60s"},
                    {"input": "I_A", "value": 400, "at": "2min"}],
        "horizon": "3min",
    }  # fmt: skip
    schedule, changes, horizon, options = parse_forecast_request(body, LIMITS, [375, 23, 50])
    assert horizon == 180 and schedule.shape == (180, 3)
    assert schedule[59].tolist() == [375, 23, 50] and schedule[60].tolist() == [375, 26, 50]
    assert schedule[120].tolist() == [400, 26, 50] and schedule[-1].tolist() == [400, 26, 50]
    assert options == {"nominal_theta": False, "with_sensor_noise": False}


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"changes": [{"input": "Q_c", "value": "60", "at": "60s"}]},
         "change 1: Q_c 60 sccm is outside this machine's limits 15–35 sccm"),
        ({"changes": [{"input": "Q_c", "value": "abc", "at": "60s"}]}, "'abc' is not a number"),
        ({"changes": [{"input": "Q_x", "value": "20", "at": "60s"}]}, "unknown input 'Q_x'"),
        ({"changes": [{"input": "Q_c", "value": "20", "at": "soon"}]}, "cannot read 'soon'"),
        ({"changes": [{"input": "Q_c", "value": "20", "at": "40min"}]}, "not before the end"),
        ({"horizon": "9h"}, "horizon must be between"),
        ({"inputs_now": [375, 23]}, "three values"),
        ("Q_c=26", "JSON object"),
    ],
)  # fmt: skip
def test_forecast_request_errors_are_sentences(body, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(")):
        parse_forecast_request(body, LIMITS, [375, 23, 50])


def test_advise_request():
    ok = parse_advise_request({"target": "40", "max_overspray": "", "settle": "2min"})
    assert ok == {
        "target": 40.0,
        "max_overspray": None,
        "settle_s": 120,
        "nominal_theta": False,
        "anyway": False,
    }
    with pytest.raises(InputError, match="outside the output model's range 1–200 µm"):
        parse_advise_request({"target": "-3"})
    with pytest.raises(InputError, match="max overspray must be > 0"):
        parse_advise_request({"target": "40", "max_overspray": "0"})
    with pytest.raises(InputError, match="target linewidth: 'x' is not a number"):
        parse_advise_request({"target": "x"})


def test_access_rules(store):
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5")
    check_access("127.0.0.1", None)
    check_access("0.0.0.0", "a-long-token")
    runner = CliRunner()
    # beyond localhost without a token: refused before anything is bound
    res = runner.invoke(dashboard, ["--store", str(store), "--host", "0.0.0.0"])
    assert res.exit_code == 2 and "give an access token with --token" in res.output
    res = runner.invoke(dashboard, ["--store", str(store), "--host", "0.0.0.0", "--token", "x"])
    assert res.exit_code == 2 and "at least 8 characters" in res.output
    res = runner.invoke(dashboard, ["--store", str(store.parent / "none.sqlite")])
    assert res.exit_code == 1 and "no registry at" in res.output
    assert not (store.parent / "none.sqlite").exists()  # the dashboard never creates one
    res = runner.invoke(
        dashboard,
        ["--store", str(store), "--virtual-print", "nozzle_clog", "--virtual-minutes", "2"],
    )
    assert res.exit_code == 2 and "onset 3 min must lie within the 2-min print" in res.output


def test_in_process_server_pushes_published_samples(store):
    """Path (b): a live engine in this process publishes; a websocket client receives."""
    import json
    import urllib.request

    from websockets.sync.client import connect

    from ajtwin.web.server import BackgroundServer

    pub = LivePublisher()
    server = BackgroundServer(store, pub, port=0)
    try:
        with urllib.request.urlopen(server.url + "api/fleet", timeout=10) as r:
            assert [m["name"] for m in json.loads(r.read())["machines"]] == [
                "alpha", "beta", "gamma"
            ]  # fmt: skip
        url = server.url.replace("http", "ws") + "ws?machine=alpha"
        with connect(url, open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["type"] == "hello"
            pub.publish({"machine": "gamma", "time_s": 1.0})  # another machine: filtered out
            pub.publish({"machine": "alpha", "time_s": 2.0, "states": [3.5, 1, 0, 0.1, 4e-7]})
            event = json.loads(ws.recv(timeout=10))
        assert event["machine"] == "alpha" and event["time_s"] == 2.0
        assert event["states"][3] == 0.1 and event["type"] == "sample"
        with urllib.request.urlopen(server.url + "api/fleet", timeout=10) as r:
            fleet = {m["name"]: m for m in json.loads(r.read())["machines"]}
        assert fleet["alpha"]["status"] == "printing"
        assert fleet["alpha"]["states"][2]["mean"] == 0.1  # ΔR_N now, from the live sample
    finally:
        server.stop()
    with pytest.raises(click_usage_error()):
        BackgroundServer(store, pub, host="0.0.0.0", port=0)


def click_usage_error():
    import click

    return click.UsageError


def test_engine_messages_become_samples():
    """The live engine's step message (values by name, raised events) → dashboard samples."""
    import dataclasses

    from ajtwin.engine.messages import StepMessage
    from ajtwin.model.names import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES
    from ajtwin.web.publisher import sample_from_engine

    states = dict(zip(STATE_NAMES, [3.5, 0.99, 1e-4, 0.05, 4.6e-7]))
    message = StepMessage(
        machine="aj1", step=200, time_s=200.0, provisional=False,
        states=states, stds=dict(zip(STATE_NAMES, [0.03, 0.003, 1e-3, 6e-4, 1e-8])),
        covariance=np.diag([0.03, 0.003, 1e-3, 6e-4, 1e-8]) ** 2,
        predicted_outputs=dict(zip(OUTPUT_NAMES, [75.0, 8.0, 5800.0, 5750.0, 1.5e-8])),
        measured_outputs=dict(zip(OUTPUT_NAMES, [76.0, 8.1, 5810.0, float("nan"), 1.4e-8])),
        inputs=dict(zip(INPUT_NAMES, [375.0, 23.0, 50.0])), nis=4.2, n_measured=4,
        reinitialised=False, theta=dict(zip(STATE_NAMES, [0.0] * 5)), em_running=False,
        nis_p=1e-3, window_nis_p=1e-12,
        cusum={"L_w": 1.0, "L_o": 0.5, "P_c": 17.0, "P_s": 12.0, "Q_m": 3.0, "P_c+P_s": 20.0},
        status="alarm", cause="nozzle_clog",
        events=(
            {"state": "raised", "detected_s": 200.0, "onset_s": 181.0, "cause": "nozzle_clog",
             "description": "nozzle clog", "detectors": ["cusum+ P_c", "cusum+ P_c+P_s"]},
            {"state": "final", "detected_s": 90.0, "onset_s": 80.0, "cause": "unexplained",
             "description": "old", "detectors": []},
        ),
    )  # fmt: skip
    s = sample_from_engine(message)
    assert s["states"] == [3.5, 0.99, 1e-4, 0.05, 4.6e-7] and s["state_stds"][3] == 6e-4
    assert s["predicted"][2] == 5800.0 and s["inputs"] == [375.0, 23.0, 50.0]
    assert s["detectors"]["cusum"] == [1.0, 0.5, 17.0, 12.0, 3.0, 20.0]
    # h per channel: 16 σ but for P_c and P_s on their own, 24 σ (a gauge's slow noise);
    # Q_m at k = 0.7, h = 16.
    assert s["detectors"]["cusum_thresholds"] == [16.0, 16.0, 24.0, 24.0, 16.0, 16.0]
    assert s["detectors"]["window_nis_log10p"] == pytest.approx(12.0)
    assert s["alarms"] == [
        {"detected_s": 200.0, "onset_s": 181.0, "cause": "nozzle_clog",
         "description": "nozzle clog", "detectors": "cusum+ P_c, cusum+ P_c+P_s"}
    ]  # fmt: skip
    assert sample_from_engine(dataclasses.replace(message, provisional=True)) is None
    pub = LivePublisher()
    pub.publish_engine(message)
    assert pub.latest("aj1")["measured"][3] is None  # NaN → None for JSON
    assert pub.alarms("aj1")[0]["cause"] == "nozzle_clog"


def test_link_state_pushed_and_rendered_on_fleet_and_machine(store):
    """The live link's state (engine message without a step) → pushed to the machine's page,
    kept for /api/machine and drawn as a badge in the fleet rows."""
    import json
    import urllib.request

    from websockets.sync.client import connect

    from ajtwin.engine.messages import LinkMessage, LinkState
    from ajtwin.web.server import BackgroundServer

    pub = LivePublisher()
    server = BackgroundServer(store, pub, port=0)
    lost = {"state": "reconnecting", "url": "opc.tcp://127.0.0.1:4840", "since": 3600.0,
            "attempt": 3, "retry_in_s": 4.0, "reason": "ConnectionRefusedError",
            "gap_s": None}  # fmt: skip
    try:
        with connect(server.url.replace("http", "ws") + "ws?machine=alpha", open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["type"] == "hello"
            pub.publish_engine(LinkMessage("beta", LinkState(**{**lost, "attempt": 1})))
            pub.publish_engine(LinkMessage("alpha", LinkState(**lost)))  # the one followed
            event = json.loads(ws.recv(timeout=10))
        assert event["type"] == "link" and event["machine"] == "alpha"
        assert event["link"]["attempt"] == 3 and event["link"]["since"] == 3600.0
        text = (
            "link lost since 01:00:00 UTC (ConnectionRefusedError) — reconnecting (attempt 3, "
            "next in 4 s)"
        )
        assert event["link"]["text"] == text
        with urllib.request.urlopen(server.url + "api/machine/alpha", timeout=10) as r:
            machine = json.loads(r.read())
        assert machine["link"]["text"] == text and machine["live"]["samples"] == []
        assert machine["status"] == "idle"  # the link state alone is not a live print
        with urllib.request.urlopen(server.url + "fragment/fleet-rows", timeout=10) as r:
            rows = r.read().decode()
        alpha = next(r for r in rows.split("<tr") if 'data-machine="alpha"' in r)
        assert '<span class="link reconnecting" title="ConnectionRefusedError">' in alpha
        assert text in alpha
        gamma = next(r for r in rows.split("<tr") if 'data-machine="gamma"' in r)
        assert 'class="link' not in gamma  # no live link for gamma
        up = LinkState(**{**lost, "state": "connected", "attempt": 0, "gap_s": 12.4})
        pub.publish_engine(LinkMessage("alpha", up))
        with urllib.request.urlopen(server.url + "fragment/fleet-rows", timeout=10) as r:
            rows = r.read().decode()
        alpha = next(r for r in rows.split("<tr") if 'data-machine="alpha"' in r)
        assert 'class="link connected"' in alpha
        assert "link up (back after a 12 s gap: missing data)" in alpha
    finally:
        server.stop()


def test_fleet_and_machine_page_agree_on_mismatch_versus_alarm(tmp_path):
    """The guard's own 'mismatch, not a fault' events make the status mismatch on both pages;
    a fault alarm in the same latest print makes it alarm on both (they used to disagree)."""
    from ajtwin.apps.detection.mismatch import MISMATCH_CAUSE
    from ajtwin.web.app import _status

    guard = {"mismatch": True, "first_s": 30.0, "outputs": ["carrier_pressure_Pa"], "states": [],
             "reasons": [], "fixes": [],
             "message": "model–machine mismatch: P_c above"}  # fmt: skip
    relabelled = AnomalyEvent(74.0, 59.0, MISMATCH_CAUSE, "model–machine mismatch, not a fault", [])
    clog = AnomalyEvent(40.0, 31.0, "nozzle_clog", "nozzle clog", ["x"])
    store = tmp_path / "r.sqlite"
    reg = Registry(store)
    for name, events in (("only-guard", [relabelled]), ("guard-and-clog", [relabelled, clog])):
        reg.add_machine(name)
        t = np.arange(5.0)
        reg.save_print(name, NewPrint(
            content_hash=name, source="hand-made", meta={}, n_samples=5, duration_s=5.0,
            summary={"mean_nis": 1.0, "mismatch": guard},
            start_mean=np.array([3.5, 1, 0, 0, 4.6e-7]), start_cov=np.eye(5) * 1e-4,
            end_mean=np.array([3.5, 1, 0, 0, 4.6e-7]), end_cov=np.eye(5) * 1e-4,
            theta_before=np.zeros(5), theta_after=np.zeros(5),
            arrays={"time_s": t, "means": np.zeros((5, 5)), "stds": np.ones((5, 5))},
            anomalies=events,
        ), expected_last_seq=None)  # fmt: skip
    reg.close()
    view, pub = RegistryView(store), LivePublisher()
    fleet = {m["name"]: m["status"] for m in view.fleet()}
    detail = {n: _status(view.machine(n), pub) for n in fleet}
    assert fleet == detail == {"only-guard": "mismatch", "guard-and-clog": "alarm"}


def test_fleet_headline_is_the_first_unresolved_fault_with_the_rest_beneath(tmp_path):
    from ajtwin.store.calibration import record_maintenance
    from ajtwin.web.pages import fleet_rows

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m")
    clog = AnomalyEvent(3630.0, 3610.0, "nozzle_clog", "nozzle clog (both pressures rising)")
    leak = AnomalyEvent(4356.0, 4338.0, "carrier_leak", "carrier leak, MFC drift or sensor")
    hand_print(reg, "m", seq_before=None, anomalies=[clog, leak])
    reg.close()
    m = RegistryView(tmp_path / "r.sqlite").fleet()[0]
    assert m["alarm"]["cause"] == "nozzle_clog"  # the first, not the last
    assert [a["cause"] for a in m["other_alarms"]] == ["carrier_leak"]
    row = fleet_rows([m])
    assert row.index("nozzle clog") < row.index("also: carrier leak at 72.6 min")
    # a cleaned nozzle resolves the clog: the leak is what is left to see
    reg = Registry(tmp_path / "r.sqlite")
    record_maintenance(reg, "m", nozzle_cleaned=True)
    reg.close()
    m = RegistryView(tmp_path / "r.sqlite").fleet()[0]
    assert m["alarm"]["cause"] == "carrier_leak"
    assert [a["cause"] for a in m["other_alarms"]] == ["nozzle_clog"]


def test_a_growing_clog_is_one_event_and_the_fleet_headline(tmp_path):
    """nozzle_clog seed 4 (90 min, the deposit ×50 from 60 min): EM's θ_RN over-predicts the
    growing deposit between updates and both pressures read low; that is the clog, not a
    'carrier leak' event at 72.6 min."""
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.simulation import simulate
    from ajtwin.web.pages import fleet_rows

    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m")
    record = simulate("nozzle_clog", seed=4)
    result = ingest_record(reg, "m", record)
    reg.close()
    onset = record.meta["fault_onset_s"]
    after = [e for e in result.events if e.detected_s >= onset]
    assert [e.cause for e in after] == ["nozzle_clog"], [(e.cause, e.detected_s) for e in after]
    assert after[0].detected_s - onset < 60.0
    m = RegistryView(tmp_path / "r.sqlite").fleet()[0]
    assert m["alarm"]["cause"] == "nozzle_clog" and m["other_alarms"] == []
    row = fleet_rows([m])
    assert "nozzle clog" in row and "carrier leak" not in row
    # φ_A in ppm by volume, the unit named in the fleet's header
    phi = m["states"][1]
    assert phi["unit"] == "ppm" and phi["scale"] == 1e6
    assert f"{phi['mean'] * 1e6:.4g} ppm" in row
