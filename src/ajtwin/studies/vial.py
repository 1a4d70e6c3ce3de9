"""The vial: V_l observable and honestly uncertain, ink running low labelled.

Before (the twin updating V_l from the generation signature, detectors on the twin's
V_l) against after (V_l a consider state in the twin, the vial observer beside it,
``ajtwin.estimation.vial``), on the same virtual prints:

* ``ink_running_low`` seeds 1–5: the cause of the first alarm event (target: ink_low on
  ≥ 4 of 5) and every event's cause;
* clean prints — ``exp1`` and ``exp2`` seeds 1–5, ``clean_long`` seeds 0–1 (8 h each):
  alarm events (target: no new ones);
* ``atomizer_dropout`` seeds 1–5: still labelled atomizer;
* V_l error at 30/60/90 min and ±2σ coverage on ``exp1``/``exp2`` seeds 1–5 (target:
  within 10 %, coverage 85–99 %), for the twin's V_l and for the observer's;
* the same on the SECOND truth generator (``--truth alt``: evaluation only, it tuned
  nothing): exp1, exp2 and ink_running_low seeds 1–5.

The twin is told the vial's fill (the scenario's initial volume, weighed at loading,
σ 3 µL as in noise.toml); ``ink_running_low`` is also run with the twin told 1.0 mL
(a fill nobody weighed) to show what the fill is worth.

    python -m ajtwin.studies.vial [--quick] [--cache DIR] [--out DIR]

``main()`` without arguments runs ``--quick`` (seed 1, 20-min prints)
and writes beside the cache, not into docs/.

Twin runs are cached as .npz (``--cache``, default /tmp/ajtwin-bench-vial), so the
tables can be rebuilt in seconds. Writes ``results.json`` and ``results.md`` to
``--out`` (default docs/results/vial).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ajtwin.apps.detection.batch import detect_anomalies
from ajtwin.estimation import Twin
from ajtwin.estimation.vial import observe_vial
from ajtwin.simulation import simulate
from ajtwin.studies import machine_description
from ajtwin.studies.detection import KEYS, detector_arrays

CHECK_MIN = (30, 60, 90)


def _case(scenario, seed, truth, variant, cache: Path, duration_min=None) -> dict:
    """Simulate, run the twin (variant: before / after / after_fill_1.0), cache arrays."""
    name = f"{scenario}_s{seed}_{truth}_{variant}" + (f"_d{duration_min:g}" if duration_min else "")
    path = cache / f"{name}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}

    rec = simulate(scenario, seed=seed, duration_min=duration_min, truth_generator=truth)
    fill = float(rec.meta["scenario_config"]["initial"]["vial_volume_mL"])
    if variant == "after_fill_1.0":
        fill = 1.0
    twin = Twin.default(vial_fill_ml=fill, vial_consider=variant != "before")
    t0 = time.process_time()
    run = twin.run(rec)
    out = {
        **detector_arrays(run, rec),
        "stds": run.stds,
        "fill": np.array(fill),
        "cpu_s": np.array(time.process_time() - t0),
    }
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    return out


def _evaluate(arrays: dict, variant: str) -> dict:

    inputs = None if variant == "before" else arrays["inputs"]
    det = detect_anomalies(*(arrays[k] for k in KEYS), inputs=inputs)
    truth = arrays["true_states"][:, 1]
    n = len(truth)
    ks = [min(int(m * 60) - 1, n - 1) for m in CHECK_MIN]

    def metrics(mean, std):
        return {
            "err_pct": [float(100 * abs(mean[k] - truth[k]) / truth[k]) for k in ks],
            "max_err_pct": float(100 * np.max(np.abs(mean - truth) / truth)),
            "coverage": float(np.mean(np.abs(mean - truth) <= 2 * std)),
        }

    out = {
        "events": [
            {"detected_s": e.detected_s, "cause": e.cause, "detectors": e.detectors}
            for e in det.events
        ],
        "twin_vial": metrics(arrays["means"][:, 1], arrays["stds"][:, 1]),
        "coverage_other": {
            name: float(
                np.mean(
                    np.abs(arrays["means"][:, i] - arrays["true_states"][:, i])
                    <= 2 * arrays["stds"][:, i]
                )
            )
            for i, name in ((0, "d_a"), (3, "ΔR_N"), (4, "φ_A"))
        },
    }
    if variant != "before":
        fill = float(arrays["fill"])
        sd = float(np.sqrt(arrays["covariances"][0, 1, 1]))
        est = observe_vial(arrays["inputs"], arrays["measurements"][:, 4], fill, sd)
        out["observer_vial"] = metrics(est.vial_ml, est.vial_std_ml)
        out["observer_first_running_low_s"] = est.first_running_low_s(arrays["time_s"])
        below = np.flatnonzero(truth < 0.5)
        out["truth_below_0.5_s"] = float(arrays["time_s"][below[0]]) if len(below) else None
        out["observer_held_s"] = int(est.held.sum())
        if variant == "after_fill_1.0":
            # the same wrong fill declared as not weighed (σ 0.3 mL): the data may move it
            est = observe_vial(arrays["inputs"], arrays["measurements"][:, 4], fill, 0.3)
            out["observer_unweighed_vial"] = metrics(est.vial_ml, est.vial_std_ml)
            out["observer_unweighed_first_running_low_s"] = est.first_running_low_s(
                arrays["time_s"]
            )
    return out


def main(argv=None) -> dict:
    """Run the vial study (``--quick``: 1 seed of 20-min prints); its figures."""
    if argv is None:  # called without arguments: the quick version
        argv = ["--quick"]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 seed, 20-min prints")
    ap.add_argument("--cache", default="/tmp/ajtwin-bench-vial")
    ap.add_argument("--out", default=None, help="default docs/results/vial (quick: the cache)")
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = str(
            Path(args.cache) / "quick" if args.quick else Path("docs") / "results" / "vial"
        )
    cache = Path(args.cache)
    seeds = (1,) if args.quick else (1, 2, 3, 4, 5)
    duration = 20.0 if args.quick else None
    plan = []
    for truth in ("model", "alt"):
        for scenario in ("ink_running_low", "exp1", "exp2"):
            for variant in ("before", "after"):
                plan += [(scenario, s, truth, variant, duration) for s in seeds]
        plan += [("ink_running_low", s, truth, "after_fill_1.0", duration) for s in seeds]
    for variant in ("before", "after"):
        # whole prints even in --quick: the dropout starts at 50 min
        plan += [("atomizer_dropout", s, "model", variant, None) for s in seeds]
        long_seeds = (0,) if args.quick else (0, 1)
        long_min = 20.0 if args.quick else None
        plan += [("clean_long", s, "model", variant, long_min) for s in long_seeds]
    t0 = time.perf_counter()
    rows = []
    for i, (scenario, seed, truth, variant, dur) in enumerate(plan):
        arrays = _case(scenario, seed, truth, variant, cache, dur)
        row = {"scenario": scenario, "seed": seed, "truth": truth, "variant": variant}
        row.update(_evaluate(arrays, variant))
        rows.append(row)
        first = row["events"][0]["cause"] if row["events"] else "-"
        print(
            f"[{i + 1}/{len(plan)}] {scenario} s{seed} {truth} {variant}: "
            f"{len(row['events'])} event(s), first {first}; twin V_l cover "
            f"{row['twin_vial']['coverage']:.2f}",
            flush=True,
        )
    result = {
        "command": "python -m ajtwin.studies.vial" + (" --quick" if args.quick else ""),
        "computer": machine_description(),
        "wall_s": time.perf_counter() - t0,
        "rows": rows,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "results.md").write_text(_markdown(result))
    print(_markdown(result))
    return _figures(rows, result["wall_s"])


def _figures(rows, wall_s) -> dict:
    """Flat named figures (name → value) of the run."""
    figures = {"wall_s": round(wall_s, 1)}
    for truth in ("model", "alt"):
        for variant in ("before", "after"):
            sel = _pick(rows, "ink_running_low", truth, variant)
            hits = sum(bool(r["events"]) and r["events"][0]["cause"] == "ink_low" for r in sel)
            figures[f"ink_running_low_{truth}_{variant}_ink_low_first_events"] = (
                f"{hits}/{len(sel)}"
            )
    for variant in ("before", "after"):
        clean = [
            r
            for scenario in ("exp1", "exp2", "clean_long")
            for r in _pick(rows, scenario, "model", variant)
        ]
        figures[f"clean_prints_events_{variant}"] = sum(len(r["events"]) for r in clean)
        exp1 = _pick(rows, "exp1", "model", variant)
        figures[f"exp1_twin_vial_coverage_min_{variant}"] = round(
            min(r["twin_vial"]["coverage"] for r in exp1), 3
        )
    return figures


def _pick(rows, scenario, truth, variant):
    return [
        r for r in rows if (r["scenario"], r["truth"], r["variant"]) == (scenario, truth, variant)
    ]


def _markdown(result) -> str:
    rows = result["rows"]
    lines = [
        "# The vial: before/after",
        "",
        f"Command: `{result['command']}`  ",
        "Computer: {}; wall {:.0f} s (twin runs cached).".format(
            result["computer"], result["wall_s"]
        ),
        "",
        "## ink_running_low: cause of the first alarm event (target: ink_low on ≥ 4 of 5)",
        "",
        "| generator | variant | first-event cause per seed | ink_low "
        "| observer 'running low' at [s] (truth < 0.5 mL at [s]) |",
        "|---|---|---|---|---|",
    ]
    for truth in ("model", "alt"):
        for variant in ("before", "after", "after_fill_1.0"):
            sel = _pick(rows, "ink_running_low", truth, variant)
            if not sel:
                continue
            causes = [r["events"][0]["cause"] if r["events"] else "none" for r in sel]
            hits = sum(c == "ink_low" for c in causes)
            when = ", ".join(
                f"{r.get('observer_first_running_low_s', float('nan')):.0f} "
                f"({r.get('truth_below_0.5_s') or float('nan'):.0f})"
                for r in sel
            )
            lines.append(
                f"| {truth} | {variant} | {' / '.join(causes)} | {hits}/{len(sel)} | "
                f"{when if variant != 'before' else '–'} |"
            )
    lines += [
        "",
        "Told 1.0 mL but declared *not weighed* (fill σ 0.3 mL), the observer alone: "
        "'running low' at [s] / max V_l error / coverage:",
        "",
    ]
    for truth in ("model", "alt"):
        sel = _pick(rows, "ink_running_low", truth, "after_fill_1.0")
        cells = [
            f"{r['observer_unweighed_first_running_low_s']:.0f} s / "
            f"{r['observer_unweighed_vial']['max_err_pct']:.0f} % / "
            f"{100 * r['observer_unweighed_vial']['coverage']:.0f} %"
            for r in sel
            if "observer_unweighed_vial" in r
        ]
        lines.append(f"- {truth}: " + "; ".join(cells))
    lines += [
        "",
        "## Alarm events on clean prints (target: no new ones) and the atomizer's label",
        "",
        "| prints | generator | before: events (causes) | after: events (causes) |",
        "|---|---|---|---|",
    ]
    for scenario, truth in (
        ("exp1", "model"),
        ("exp2", "model"),
        ("clean_long", "model"),
        ("exp1", "alt"),
        ("exp2", "alt"),
        ("atomizer_dropout", "model"),
    ):
        cells = []
        for variant in ("before", "after"):
            sel = _pick(rows, scenario, truth, variant)
            causes = [e["cause"] for r in sel for e in r["events"]]
            cells.append(f"{len(causes)} ({', '.join(causes) or '–'})")
        seeds = sorted({r["seed"] for r in _pick(rows, scenario, truth, "after")})
        lines.append(f"| {scenario} seeds {seeds} | {truth} | {cells[0]} | {cells[1]} |")
    lines += [
        "",
        "## V_l: error at 30/60/90 min (worst seed) and ±2σ coverage (per seed)",
        "",
        "| prints | generator | estimate | worst err 30/60/90 [%] | max err [%] "
        "| coverage per seed |",
        "|---|---|---|---|---|---|",
    ]
    for scenario in ("exp1", "exp2", "ink_running_low"):
        for truth in ("model", "alt"):
            for variant, key, label in (
                ("before", "twin_vial", "twin (before)"),
                ("after", "twin_vial", "twin, consider (after)"),
                ("after", "observer_vial", "vial observer (after)"),
            ):
                sel = _pick(rows, scenario, truth, variant)
                if not sel:
                    continue
                err = np.max([r[key]["err_pct"] for r in sel], axis=0)
                cover = " / ".join(f"{100 * r[key]['coverage']:.0f}" for r in sel)
                mx = max(r[key]["max_err_pct"] for r in sel)
                lines.append(
                    f"| {scenario} | {truth} | {label} | "
                    f"{err[0]:.2f}/{err[1]:.2f}/{err[2]:.2f} | {mx:.2f} | {cover} % |"
                )
    lines += [
        "",
        "## The other states' ±2σ coverage, mean over seeds (before → after)",
        "",
        "| prints | generator | d_a | ΔR_N | φ_A |",
        "|---|---|---|---|---|",
    ]
    for scenario in ("exp1", "exp2"):
        for truth in ("model", "alt"):
            cells = []
            for name in ("d_a", "ΔR_N", "φ_A"):
                b = np.mean(
                    [r["coverage_other"][name] for r in _pick(rows, scenario, truth, "before")]
                )
                a = np.mean(
                    [r["coverage_other"][name] for r in _pick(rows, scenario, truth, "after")]
                )
                cells.append(f"{100 * b:.1f} → {100 * a:.1f} %")
            lines.append(f"| {scenario} | {truth} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main(sys.argv[1:])
