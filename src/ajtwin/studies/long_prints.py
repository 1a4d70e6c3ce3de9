"""The detectors over long clean prints: events per 10 print-hours, by hour, and the
'nozzle needs cleaning' event once the deposit leaves the output model's range.

A clean first-generator print (``exp1``) of 24 h or 7 days: the nozzle's ordinary deposit
grows ~18 nm per hour and passes the output model's range (0.5 µm, ``data/detectors.toml``
[nozzle_cleaning]) after ~27 h. The twin's run is cached (``.npz``) so that detector
settings are compared in seconds: as shipped, without the windowed NIS's long-run scale,
and with neither it nor the cleaning event (the detectors before them).

    python -m ajtwin.studies.long_prints [--seeds 5] [--minutes 1440] [--cache DIR]
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import click
import numpy as np

from ajtwin.apps.detection.batch import DETECTOR_ARRAYS, detect_anomalies
from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.estimation import Twin
from ajtwin.simulation import simulate

KEYS = (*DETECTOR_ARRAYS, "inputs")


def twin_arrays(seed: int, minutes: float, cache: Path) -> dict:
    """The twin's run over clean print ``exp1`` ``seed`` of ``minutes``, cached in ``cache``."""
    path = cache / f"exp1-seed{seed}-{minutes:g}min.npz"
    if path.exists():
        with np.load(path) as data:
            return {k: data[k] for k in KEYS}
    record = simulate("exp1", seed=seed, duration_min=minutes)
    run = Twin.default().run(record)
    f = run.filtered
    arrays = {
        "time_s": run.time_s,
        "measurements": record.outputs,
        "predicted_outputs": np.asarray(f.predicted_outputs),
        "innovation_variances": np.asarray(f.innovation_variances),
        "nis": np.asarray(f.nis),
        "n_measured": np.asarray(f.n_measured),
        "means": np.asarray(f.means),
        "predicted_means": np.asarray(f.predicted_means),
        "covariances": np.asarray(f.covariances),
        "inputs": record.inputs,
    }
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return arrays


SETTINGS = {
    "as shipped": {},
    "windowed NIS unscaled": {"nis_long_run_scaled": False},
    "before (unscaled, no cleaning event)": {
        "nis_long_run_scaled": False,
        "cleaning_deposit_um": np.inf,
    },
}


def summarise(arrays: dict, label: str, overrides: dict) -> dict:
    """Events of the detectors under ``overrides``: count, rate before the cleaning event,
    by label, and the hours they came at."""
    settings = replace(DetectorSettings(), **overrides)
    result = detect_anomalies(**{k: arrays[k] for k in KEYS if k != "inputs"},
                              settings=settings, inputs=arrays["inputs"])  # fmt: skip
    events = result.events
    hours = (arrays["time_s"][-1] - arrays["time_s"][0] + 1) / 3600
    cleaning = next((e for e in events if e.cause == "nozzle_cleaning"), None)
    before = [e for e in events if cleaning is None or e.detected_s < cleaning.detected_s]
    span_h = hours if cleaning is None else (cleaning.detected_s - arrays["time_s"][0]) / 3600
    labels: dict[str, int] = {}
    for e in events:
        labels[e.cause] = labels.get(e.cause, 0) + 1
    return {
        "settings": label,
        "events": len(events),
        "per_10_h_before_cleaning": 10 * len(before) / max(span_h, 1e-9),
        "cleaning_at_h": None if cleaning is None else cleaning.detected_s / 3600,
        "labels": labels,
        "event_hours": [round(e.detected_s / 3600, 2) for e in events[:12]],
    }


@click.command()
@click.option("--seeds", default="5", show_default=True, help="exp1 seeds, comma-separated.")
@click.option("--minutes", type=float, default=1440.0, show_default=True)
@click.option("--cache", type=click.Path(path_type=Path), default=Path("/tmp/ajtwin-long-prints"))
def main(seeds, minutes, cache):
    """Print the detectors' events over long clean prints under each setting."""
    for seed in (int(v) for v in seeds.split(",")):
        t0 = time.perf_counter()
        arrays = twin_arrays(seed, minutes, cache)
        print(f"exp1 seed {seed}, {minutes:g} min (twin {time.perf_counter() - t0:.0f} s)")
        print(f"  end ΔR_N {arrays['means'][-1, 3]:.3f} µm")
        for label, overrides in SETTINGS.items():
            row = summarise(arrays, label, overrides)
            print(
                f"  {label:38s} {row['events']:4d} events, "
                f"{row['per_10_h_before_cleaning']:.2f} per 10 h before the cleaning event, "
                f"cleaning at {row['cleaning_at_h']} h; {row['labels']}; first at h "
                f"{row['event_hours']}"
            )


if __name__ == "__main__":
    main()
