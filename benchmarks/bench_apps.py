"""Figures of the applications: detection delay per fault, false alarms on clean_long,
ingest / forecast / advise timings.

    .venv/bin/python benchmarks/bench_apps.py            # ~10 min cold, seconds when cached

Twin runs over the scenarios are cached in /tmp/ajtwin-anomaly-cache (ajtwin.apps.evaluate);
delete it to re-measure from scratch. Fault scenarios: seeds 0-2 (90 min each); clean_long:
seeds 0 and 1 (8 h each).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

CACHE = os.environ.get("AJTWIN_ANOMALY_CACHE", "/tmp/ajtwin-anomaly-cache")


def detection_figures() -> dict:
    from ajtwin.apps.evaluate import evaluate

    result = evaluate(CACHE, seeds=(0, 1, 2), clean_seeds=(0, 1), progress=None)
    out = {}
    for scenario in sorted({r["scenario"] for r in result["faults"]}):
        rows = [r for r in result["faults"] if r["scenario"] == scenario]
        delays = [r["delay_s"] for r in rows]
        out[f"{scenario}_delay_s_per_seed"] = delays
        out[f"{scenario}_cause_correct"] = sum(r["cause"] == r["expected_cause"] for r in rows)
        out[f"{scenario}_false_alarms_before_onset"] = sum(
            r["false_alarms_before_onset"] for r in rows
        )
    out["clean_long_hours"] = round(result["clean_hours"], 2)
    out["clean_long_alarm_events"] = result["false_alarm_events"]
    out["false_alarms_per_10_print_hours"] = result["false_alarms_per_10h"]
    return out


def timing_figures() -> dict:
    from ajtwin.apps.planning.advice import advise
    from ajtwin.apps.planning.forecast import forecast, input_schedule, parse_change
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.estimation import Twin
    from ajtwin.simulation import simulate
    from ajtwin.store.registry import Registry

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        reg = Registry(Path(tmp) / "r.sqlite")
        reg.add_machine("bench")
        first = simulate("exp1", seed=5, duration_min=30)
        second = simulate("exp1", seed=6, duration_min=30, continue_from=first)
        t0 = time.perf_counter()
        ingest_record(reg, "bench", first)
        out["ingest_30min_print_first_s"] = round(time.perf_counter() - t0, 2)
        t0 = time.perf_counter()
        res = ingest_record(reg, "bench", second)
        out["ingest_30min_print_warm_s"] = round(time.perf_counter() - t0, 2)
        out["ingest_twin_share_warm"] = None if res.seconds == 0 else 1.0
        t0 = time.perf_counter()
        ingest_record(reg, "bench", second)
        out["ingest_duplicate_check_s"] = round(time.perf_counter() - t0, 3)
        size = (Path(tmp) / "r.sqlite").stat().st_size
        wal = Path(tmp) / "r.sqlite-wal"
        size += wal.stat().st_size if wal.exists() else 0
        out["registry_bytes_per_print_hour"] = int(size / 1.0)
        last = reg.last_print("bench")
        twin = Twin.default()
        twin.theta = last["theta_after"]
        u = input_schedule([375, 23, 50], [parse_change("Q_c=26@+60s")], 1800)
        t0 = time.perf_counter()
        forecast(twin, last["end_mean"], last["end_cov"], u)
        out["forecast_30min_first_call_s"] = round(time.perf_counter() - t0, 2)
        t0 = time.perf_counter()
        forecast(twin, last["end_mean"], last["end_cov"], u)
        out["forecast_30min_warm_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        adv = advise(twin, last["end_mean"], last["end_cov"], [375, 23, 50], 40.0)
        out["advise_first_call_s"] = round(time.perf_counter() - t0, 2)
        t0 = time.perf_counter()
        advise(twin, last["end_mean"], last["end_cov"], [375, 23, 50], 45.0)
        out["advise_warm_s"] = round(time.perf_counter() - t0, 2)
        out["advise_40um_reachable"] = bool(adv.reachable)
        reg.close()
    out.pop("ingest_twin_share_warm")
    return out


def main() -> dict:
    figures = {}
    figures.update(timing_figures())
    figures.update(detection_figures())
    figures["note"] = (
        "ingest = twin (EKF+EM) + detectors + one SQLite transaction for a 30-min print; "
        "first call includes JAX compilation. Detection: default DetectorSettings."
    )
    return figures


if __name__ == "__main__":
    print(json.dumps(main(), indent=1, default=lambda v: float(v) if np.isscalar(v) else str(v)))
