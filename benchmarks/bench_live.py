"""Live twin: per-step latency, machines per process at 1 Hz, start-up of ``ajtwin live``.

* ``step_latency_*_us``: from a sample's arrival (``LiveEngine.feed``) to its published
  message (subscriber callback), one machine, 20 min of print with EM in a worker thread.
* ``step_cpu_per_machine_us``: CPU time of one ordinary step per machine when N machines
  step together (vmapped), and ``em_cpu_s`` of one EM update (600 s window); with EM
  every 300 s, ``machines_per_process_1hz`` = the N a process keeps up with on one core
  (1 s of CPU per second of print; the EM thread can use the second core).
* ``startup_to_first_state_s``: ``ajtwin live`` launched → first published state, against
  a virtual printer already serving (loopback OPC UA).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ._figures import tracked

SRC = str(Path(__file__).resolve().parents[1] / "src")


def step_latency(pace_s: float = 0.02) -> dict:
    """Samples fed every ``pace_s`` (×50 real time): arrival → first published state
    (provisional while EM runs) and → committed state."""
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample
    from ajtwin.simulation import simulate

    rec = simulate("exp1", seed=3, duration_min=20)
    t_s, inputs, outputs = rec.time_s, rec.inputs, rec.outputs
    engine = LiveEngine(asynchronous=True)
    engine.warm_up()
    arrival, first, committed = {}, [], []
    seen = set()

    def on_message(m):
        k = m.get("step")
        if k is None or k not in arrival:
            return
        now = time.perf_counter()
        if k not in seen:
            seen.add(k)
            first.append(now - arrival[k])
        if not m["provisional"]:
            committed.append(now - arrival.pop(k))

    engine.subscribe(on_message)
    cpu0 = time.process_time()
    next_at = time.perf_counter()
    for k in range(len(t_s)):
        while time.perf_counter() < next_at:
            engine.poll_and_publish()
            time.sleep(0.001)
        next_at += pace_s
        arrival[k] = time.perf_counter()
        engine.feed("m", Sample(t_s[k], inputs[k], outputs[k]))
    stream = engine.sessions["m"].stream
    while stream.em_running:
        stream._em_future.result(timeout=300)
        engine.poll_and_publish()
    cpu = time.process_time() - cpu0
    engine.shutdown()
    first_us = np.array(first) * 1e6
    comm_us = np.array(committed) * 1e6
    return {
        "step_latency_p50_us": round(float(np.percentile(first_us, 50)), 1),
        "step_latency_p99_us": round(float(np.percentile(first_us, 99)), 1),
        "committed_latency_p50_us": round(float(np.percentile(comm_us, 50)), 1),
        "committed_latency_p99_ms": round(float(np.percentile(comm_us, 99)) / 1e3, 1),
        "committed_latency_max_s": round(float(comm_us.max()) / 1e6, 2),
        "steps_timed": int(len(first_us)),
        "cpu_per_step_incl_em_us": round(cpu / len(t_s) * 1e6, 1),
    }


def fleet_cost() -> dict:
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation import Twin
    from ajtwin.estimation.em import EMSettings, run_em
    from ajtwin.estimation.samples import Sample
    from ajtwin.simulation import simulate

    rec = simulate("exp1", seed=4, duration_min=11)
    t_s, inputs, outputs = rec.time_s, rec.inputs, rec.outputs
    out = {}
    per_machine = {}
    for n in (1, 16, 64):
        engine = LiveEngine(asynchronous=False, twin_overrides={"em": False})
        engine.warm_up(n)
        names = [f"m{i}" for i in range(n)]
        warm = 30
        for k in range(warm):
            engine.feed_many([(m, Sample(t_s[k], inputs[k], outputs[k])) for m in names])
        cpu0 = time.process_time()
        steps = 120
        for k in range(warm, warm + steps):
            engine.feed_many([(m, Sample(t_s[k], inputs[k], outputs[k])) for m in names])
        per_machine[n] = (time.process_time() - cpu0) / steps / n
        engine.shutdown()
        out[f"step_cpu_per_machine_us_n{n}"] = round(per_machine[n] * 1e6, 1)
    twin = Twin.default()
    run = twin.run(rec.window(0, 600), smooth=False)
    args = (
        twin.spec,
        run.start_mean,
        run.start_cov,
        rec.inputs[:600],
        rec.outputs[:600],
        np.zeros(5),
        twin.process_cov,
        twin.measurement_var,
    )
    kw = dict(settings=EMSettings(twin.theta_prior_precision), functions=twin.functions)
    run_em(*args, **kw)  # compile
    cpu0 = time.process_time()
    run_em(*args, **kw)
    em_cpu = time.process_time() - cpu0
    out["em_cpu_s"] = round(em_cpu, 3)
    best = min(per_machine.values())
    per_second = best + em_cpu / 300.0  # EM every 300 s, amortised
    out["cpu_per_machine_second_us"] = round(per_second * 1e6, 1)
    out["machines_per_process_1hz"] = int(1.0 / per_second)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def startup(tmp: Path) -> dict:
    # the ajtwin this process runs (an older commit's under scripts/asv_at_commit.py)
    env = dict(os.environ, PYTHONPATH=os.environ.get("PYTHONPATH") or SRC)
    url = f"opc.tcp://127.0.0.1:{_free_port()}"
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ajtwin.cli",
            "printer",
            "serve",
            "--scenario",
            "exp1",
            "--speed",
            "1",
            "--start-s",
            "600",
            "--endpoint",
            url,
        ],
        stdout=(tmp / "server.log").open("w"),
        stderr=subprocess.STDOUT,
        env=env,
    )
    live = None
    try:
        time.sleep(20)  # the server simulates its print and starts listening
        messages = tmp / "m.jsonl"
        t0 = time.perf_counter()
        live = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "ajtwin.cli",
                "live",
                "--machine",
                "aj300-01",
                "--opcua",
                url,
                "--store",
                str(tmp / "r.sqlite"),
                "--messages",
                str(messages),
            ],
            stdout=(tmp / "live.log").open("w"),
            stderr=subprocess.STDOUT,
            env=env,
        )
        first = None
        while time.perf_counter() - t0 < 180:
            if messages.exists() and '"step"' in messages.read_text():
                first = time.perf_counter() - t0
                break
            time.sleep(0.05)
        return {"startup_to_first_state_s": None if first is None else round(first, 2)}
    finally:
        for p in (live, server):
            if p is not None and p.poll() is None:
                os.kill(p.pid, signal.SIGTERM)
                p.wait(timeout=30)


@tracked(
    {
        "step_latency_p50_us": "µs",
        "step_latency_p99_us": "µs",
        "committed_latency_p50_us": "µs",
        "committed_latency_p99_ms": "ms",
        "cpu_per_step_incl_em_us": "µs",
        "step_cpu_per_machine_us_n1": "µs",
        "step_cpu_per_machine_us_n16": "µs",
        "step_cpu_per_machine_us_n64": "µs",
        "em_cpu_s": "s",
        "machines_per_process_1hz": "machines",
    }
)
class LiveStep:
    """One machine fed at ×50 (EM in a worker thread), and fleets stepping together."""

    timeout = 1800

    def setup_cache(self):
        figures = step_latency()
        figures.update(fleet_cost())
        return figures


@tracked({"startup_to_first_state_s": "s"})
class LiveStart:
    """``ajtwin live`` launched against a serving virtual printer → first published state."""

    timeout = 600

    def setup_cache(self):
        return startup(Path.cwd())
