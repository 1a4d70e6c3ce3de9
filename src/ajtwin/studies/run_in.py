"""Start-up prints through ``ajtwin ingest`` and ``ajtwin estimate``: false faults and mismatch.

Each start-up is a virtual print that begins as the atomizer is switched on (the ``startup``
scenario: the mist builds up over a drawn 5-15 min; its record says
``atomizer_switched_on_s``). It is ingested into a fresh machine (the detectors, the chunked
mismatch guard) and estimated (the guard over the states table), as a user runs them, and
again with the switch-on left out of the record — what the twin said before it knew of the
run-in, and what it says of a print whose log does not tell. Counted per print: the events
with a fault cause (``data/causes.toml`` ``fault = true``), those labelled ``run_in``, the
seconds ``estimate`` flags as a model–machine mismatch and whether ``ingest`` stored one.

Run: ``python -m ajtwin.studies.run_in [--seeds 1-10] [--truth model|alt]``; writes
``docs/results/ready/run_in_<truth>_<seeds>.json`` and ``.md``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import click
import numpy as np

from ajtwin.apps.detection.causes import open_faults
from ajtwin.engine.chain import open_registry
from ajtwin.engine.estimate import estimate_to_csv
from ajtwin.engine.ingest import ingest_record
from ajtwin.estimation import Twin
from ajtwin.io.records import PrintRecord
from ajtwin.simulation import simulate

OUT = Path(__file__).resolve().parents[3] / "docs" / "results" / "ready"
DURATION_MIN = 30.0


def one_print(record: PrintRecord, folder: Path) -> dict:
    """Ingest (a fresh machine) and estimate one record: faults, run-ins, mismatch."""
    registry = open_registry(folder / "r.sqlite")
    registry.add_machine("m1")
    ingested = ingest_record(registry, "m1", record)
    registry.close()
    done = estimate_to_csv(Twin.default(), record, folder / "states.csv")
    return {
        "fault_events": len(open_faults(ingested.events, [])),
        "run_in_events": sum(ev.cause == "run_in" for ev in ingested.events),
        "events": [[ev.onset_s, ev.detected_s, ev.cause] for ev in ingested.events],
        "ingest_mismatch": bool(ingested.summary["mismatch"]["mismatch"]),
        "estimate_mismatch_s": int(np.asarray(done.mismatch.flags).sum()),
    }


def run_study(seeds, truth: str, progress=print) -> dict:
    """Start-ups over ``seeds``, told of the switch-on and not."""
    t0 = time.perf_counter()
    rows = []
    for seed in seeds:
        record = simulate("startup", seed=seed, duration_min=DURATION_MIN, truth_generator=truth)
        untold = {k: v for k, v in record.meta.items() if k != "atomizer_switched_on_s"}
        for told, rec in ((True, record), (False, PrintRecord(record.data, untold))):
            with tempfile.TemporaryDirectory() as folder:
                row = {"seed": seed, "switch_on_told": told, **one_print(rec, Path(folder))}
            rows.append(row)
            progress(json.dumps(row))
    summary = {}
    for told in (True, False):
        part = [r for r in rows if r["switch_on_told"] is told]
        summary["told" if told else "untold"] = {
            "prints": len(part),
            "fault_events": sum(r["fault_events"] for r in part),
            "prints_with_a_fault": sum(r["fault_events"] > 0 for r in part),
            "run_in_events": sum(r["run_in_events"] for r in part),
            "ingest_mismatch_prints": sum(r["ingest_mismatch"] for r in part),
            "estimate_mismatch_prints": sum(r["estimate_mismatch_s"] > 0 for r in part),
            "estimate_mismatch_s": sum(r["estimate_mismatch_s"] for r in part),
        }
    return {"truth": truth, "rows": rows, "summary": summary, "wall_s": time.perf_counter() - t0}


def markdown(results: dict, command: str) -> str:
    """The study's table."""
    lines = [
        f"Command: `{command}` ({results['wall_s']:.0f} s)",
        "",
        "| truth | record says the switch-on | start-ups | fault events (prints) | run-in events "
        "| mismatch: ingest prints | mismatch: estimate prints, seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, words in (("told", "yes"), ("untold", "no")):
        s = results["summary"][key]
        lines.append(
            f"| {results['truth']} | {words} | {s['prints']} | {s['fault_events']} "
            f"({s['prints_with_a_fault']}) | {s['run_in_events']} | "
            f"{s['ingest_mismatch_prints']} | {s['estimate_mismatch_prints']}, "
            f"{s['estimate_mismatch_s']} s |"
        )
    return "\n".join(lines) + "\n"


@click.command()
@click.option("--seeds", default="1-10", show_default=True, help="First-last start-up seeds.")
@click.option("--truth", type=click.Choice(["model", "alt"]), default="model", show_default=True)
def main(seeds: str, truth: str) -> None:
    """Start-up prints through ingest and estimate (module docstring)."""
    first, last = (int(v) for v in seeds.split("-"))
    results = run_study(range(first, last + 1), truth)
    command = f"python -m ajtwin.studies.run_in --seeds {first}-{last} --truth {truth}"
    OUT.mkdir(parents=True, exist_ok=True)
    stem = OUT / f"run_in_{truth}_{first}-{last}"
    stem.with_suffix(".json").write_text(json.dumps(results, indent=1, default=float))
    stem.with_suffix(".md").write_text(markdown(results, command))
    click.echo(markdown(results, command))


if __name__ == "__main__":
    main()
