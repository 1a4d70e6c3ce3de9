"""Speed of the applications: ingest of a 30-min print, the duplicate check, a 30-min
forecast and input advice (first call, with JAX compilation, and warm).

    .venv/bin/python benchmarks/bench_apps.py

The detectors' accuracy (delay per fault, false alarms on clean prints) is a study:
``python -m ajtwin.studies.detection``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np


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
    figures["note"] = (
        "ingest = twin (EKF+EM) + detectors + one SQLite transaction for a 30-min print; "
        "first call includes JAX compilation."
    )
    return figures


if __name__ == "__main__":
    print(json.dumps(main(), indent=1, default=lambda v: float(v) if np.isscalar(v) else str(v)))
