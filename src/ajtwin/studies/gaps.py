"""The detectors after a data gap: false alarms on clean prints with a gap, and a fault's
delay, with and without the warm-up restart (``data/detectors.toml`` [gaps]).

A gap is what a lost OPC UA link or a hole in a machine's log leaves: seconds without any
measurement, the inputs held. Each clean first-generator print gets one gap of each length
at each position; the table counts the events the detectors raise (any event is false on a
clean print), with the restart (``gap_restart_s`` as shipped) and without it (``inf``), and
the delay of a nozzle clog whose onset follows a gap.

    python -m ajtwin.studies.gaps [--seeds 1-6] [--gaps 5,10,29,120] [--minutes 10]
"""

from __future__ import annotations

from dataclasses import replace

import click
import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.estimation import Twin
from ajtwin.io.records import OUTPUT_COLUMNS, PrintRecord
from ajtwin.simulation import simulate


def with_gap(record, start: int, length: int) -> PrintRecord:
    """``record`` with seconds [start, start + length) unmeasured and their inputs held at
    the last second before (what the record reader and the live link make of a gap)."""
    data = record.data.copy()
    stop = min(start + length, len(data))
    data.loc[data.index[start:stop], list(OUTPUT_COLUMNS)] = np.nan
    for column in ("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm"):
        data.loc[data.index[start:stop], column] = data[column].iloc[start - 1]
    return PrintRecord(data, dict(record.meta))


def events_with_and_without(record) -> tuple[list, list]:
    """(events with the restart, events without it) of the twin's run over ``record``."""
    run = Twin.default().run(record)
    shipped = DetectorSettings()
    off = replace(shipped, gap_restart_s=np.inf)
    return detect_run(run, record, shipped).events, detect_run(run, record, off).events


@click.command()
@click.option("--seeds", default="1-6", show_default=True, help="exp1 seeds (a-b or a,b).")
@click.option("--gaps", default="5,10,29,120", show_default=True, help="Gap lengths [s].")
@click.option("--minutes", type=float, default=10.0, show_default=True)
def main(seeds, gaps, minutes):
    """Print the events on clean prints with one gap, with and without the restart."""
    a, _, b = seeds.partition("-")
    seed_list = (
        list(range(int(a), int(b or a) + 1)) if "-" in seeds else [int(v) for v in seeds.split(",")]
    )
    lengths = [int(v) for v in gaps.split(",")]
    positions = (100, 250, 400)
    totals = {length: [0, 0, 0] for length in lengths}  # prints, events with, without
    for seed in seed_list:
        clean = simulate("exp1", seed=seed, duration_min=minutes)
        for length in lengths:
            for start in positions:
                on, off = events_with_and_without(with_gap(clean, start, length))
                totals[length][0] += 1
                totals[length][1] += len(on)
                totals[length][2] += len(off)
                print(
                    f"seed {seed} gap {length:4d} s at {start:4d} s: "
                    f"{len(on)} event(s) with the restart, {len(off)} without "
                    f"{[(e.detected_s, e.cause) for e in off]}"
                )
    print("\ngap [s]  prints  events with restart  events without")
    for length, (n, on, off) in totals.items():
        print(f"{length:7d}  {n:6d}  {on:19d}  {off:14d}")
    print("\nnozzle clog at 360 s after a gap ending at 330 s: first event at/after the onset")
    for seed in seed_list[:3]:
        clog = simulate(
            "nozzle_clog",
            seed=seed,
            duration_min=12,
            overrides={"fault": {"onset_min": 6.0, "nozzle_deposition_multiplier": 400.0}},
        )
        for length in lengths:
            on, off = events_with_and_without(with_gap(clog, 330 - length, length))
            first = [
                next((e.detected_s - 360 for e in evs if e.detected_s >= 360), None)
                for evs in (on, off)
            ]
            print(
                f"seed {seed} gap {length:4d} s: delay {first[0]} s with the restart, "
                f"{first[1]} s without"
            )


if __name__ == "__main__":
    main()
