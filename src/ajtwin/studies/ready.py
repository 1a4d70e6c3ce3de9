"""Ready to print: the settling detector on virtual start-ups, against the true settling.

Each start-up is a 30-min virtual print (exp1's inputs) with the atomizer's start-up
transient (:mod:`ajtwin.simulation.startup`: settled within 2 % after 5-15 min); the twin
(:class:`ajtwin.estimation.Twin`, as ``ajtwin estimate`` runs it) filters it and the detector
(:mod:`ajtwin.apps.detection.settling`) reads its states and predicted outputs. The *true*
settling is the first second after which the true noise-free L_w stays within 0.5 µm of the
same print without the start-up (the same seed: the same wander); a "ready" before it is
false. Prints without a start-up measure how soon a settled machine is called ready.

Run: ``python -m ajtwin.studies.ready [--seeds 1-20] [--truth model|alt]``; writes
``docs/results/ready/results_<truth>.json`` and ``.md``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ajtwin.apps.detection.settling import settling_time
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.printer import run_virtual_print

OUT = Path(__file__).resolve().parents[3] / "docs" / "results" / "ready"
STARTUP = {"settling_min_low": 5.0, "settling_min_high": 15.0}
DURATION_MIN = 30.0
#: the line is settled once it stays this close to the print without the start-up [µm]
TRUE_TOLERANCE_UM = 0.5


def true_settling_s(with_startup: np.ndarray, without: np.ndarray) -> float:
    """The first second after which |L_w − L_w without the start-up| stays ≤ tolerance."""
    off = np.abs(with_startup - without) > TRUE_TOLERANCE_UM
    return float(np.flatnonzero(off)[-1] + 1) if off.any() else 0.0


def one_startup(seed: int, truth: str, startup: bool, settings=None) -> dict:
    """One virtual print with (or without) the start-up: the detector's verdict and the truth."""
    overrides = {"startup": STARTUP} if startup else None
    vp = run_virtual_print("exp1", seed, DURATION_MIN, overrides, truth_generator=truth)
    run = Twin.default().run(vp.record)
    verdict = settling_time(
        run.time_s,
        np.asarray(run.filtered.means),
        np.asarray(run.filtered.predicted_outputs),
        settings,
    )
    out = {
        "seed": seed,
        "startup": startup,
        "ready": verdict.ready,
        "ready_at_s": verdict.ready_at_s,
    }
    if startup:
        base = run_virtual_print("exp1", seed, DURATION_MIN, truth_generator=truth)
        difference = np.abs(vp.outputs_true[:, 0] - base.outputs_true[:, 0])
        out["true_settling_s"] = true_settling_s(vp.outputs_true[:, 0], base.outputs_true[:, 0])
        out["drawn_settling_s"] = vp.processes.draws["startup_settling_s"]
        if verdict.ready:
            out["delay_s"] = verdict.ready_at_s - out["true_settling_s"]
            out["false_ready"] = bool(verdict.ready_at_s < out["true_settling_s"])
            # how far the line still was from its settled path when called ready [µm]
            out["remaining_um"] = float(difference[int(verdict.ready_at_s) :].max())
    return out


def run_study(seeds, truth: str, progress=print) -> dict:
    """Start-ups with and without the transient over ``seeds``."""
    t0 = time.perf_counter()
    rows = []
    for seed in seeds:
        for startup in (True, False):
            row = one_startup(seed, truth, startup)
            rows.append(row)
            progress(json.dumps(row))
    ups = [r for r in rows if r["startup"]]
    delays = np.array([r["delay_s"] for r in ups if r["ready"]])
    settled = [r for r in rows if not r["startup"]]
    summary = {
        "truth": truth,
        "startups": len(ups),
        "never_ready": int(sum(not r["ready"] for r in ups)),
        "false_ready": int(sum(r.get("false_ready", False) for r in ups)),
        "remaining_um_max": float(max((r.get("remaining_um", 0.0) for r in ups), default=0.0)),
        "delay_median_s": float(np.median(delays)) if len(delays) else None,
        "delay_p90_s": float(np.percentile(delays, 90)) if len(delays) else None,
        "true_settling_median_s": float(np.median([r["true_settling_s"] for r in ups])),
        "settled_machine_ready_median_s": float(
            np.median([r["ready_at_s"] for r in settled if r["ready"]])
        )
        if any(r["ready"] for r in settled)
        else None,
        "settled_machine_never_ready": int(sum(not r["ready"] for r in settled)),
    }
    return {"rows": rows, "summary": summary, "wall_s": time.perf_counter() - t0}


def markdown(results: dict, command: str) -> str:
    """The study's figures."""
    s = results["summary"]
    return (
        f"Command: `{command}` ({results['wall_s']:.0f} s)\n\n"
        "| truth | start-ups | false ready | never ready | delay after true settling "
        "(median / 90th pct) | "
        "true settling (median) | settled machine: ready after (median) "
        "|\n|---|---|---|---|---|---|---|\n"
        f"| {s['truth']} | {s['startups']} | {s['false_ready']} ({s['remaining_um_max']:.2f} µm) | "
        f"{s['never_ready']} | "
        f"{s['delay_median_s']:.0f} s / {s['delay_p90_s']:.0f} s | "
        f"{s['true_settling_median_s']:.0f} s | "
        f"{s['settled_machine_ready_median_s']:.0f} s ({s['settled_machine_never_ready']} "
        "never) |\n"
    )


if __name__ == "__main__":
    first, last = 1, 20
    if "--seeds" in sys.argv:
        first, last = (int(v) for v in sys.argv[sys.argv.index("--seeds") + 1].split("-"))
    generator = sys.argv[sys.argv.index("--truth") + 1] if "--truth" in sys.argv else "alt"
    OUT.mkdir(parents=True, exist_ok=True)
    results = run_study(range(first, last + 1), generator)
    cmd = f"python -m ajtwin.studies.ready --seeds {first}-{last} --truth {generator}"
    (OUT / f"results_{generator}.json").write_text(json.dumps(results, indent=1, default=float))
    (OUT / f"results_{generator}.md").write_text(markdown(results, cmd))
    print(markdown(results, cmd))
