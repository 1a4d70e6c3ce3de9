"""Measure the part quality map on virtual job prints against their truth.

A real public program (``1-nafbot.prg`` of jizhang495/prg2svg, MIT) looped to the
scenario's 90 min is printed by the virtual printer (both truth generators, several
seeds) three times per machine: with the packaged ``nozzle_clog`` fault (deposition × 50
from 60 min), with a faster clog (× 300 from 60 min: the packaged one widens the line by
0–4 µm by the print's end, no more than the line's own wander on most machines), and
clean (``exp1``, the same inputs without the fault). The twin maps each print's part as
the print ran (:func:`ajtwin.apps.quality.part_map.part_map_of_record` with the program read from
the record, :func:`ajtwin.estimation.print_time.program_for_record`: the default trailing
camera's frames filed at their print times) and the map is judged against the true line
at the sample points' print times
(:func:`ajtwin.simulation.job_print.line_at_print_times`: the truth's states, line model and
speed law at τ, not the 1 Hz ``true_linewidth_um`` rows):

* a portion is **truly out** when the true width leaves the tolerance anywhere along it
  (at any sample point), the same worst-point rule the map's probability uses;
* **precision** = flagged and truly out / flagged, **recall** = flagged and truly out /
  truly out, per stroke portion, pooled over prints; also after the onset alone;
* **coverage**: the share of the printed length where the true width lies inside the
  map's ±2σ band (aim ≥ 90 % on clean prints).

The tolerance of a machine's prints is set around the line it printed before the fault:
the median true width over the 30 min before the onset (30–60 min, the same on the three
prints of a machine: their truth is identical until the onset), rounded to 0.5 µm,
± ``half_width`` (2 µm: ±2.7 % of a 75-µm line; "45±3 µm" on a drawing is ±6.7 %, which
the packaged clog would not leave on any machine).

    python -m ajtwin.studies.part_map [--seeds 1-4] [--truth model,alt] \\
        [--out docs/results/part_map] [--figures docs/figures/part_map]

Writes ``NAME.json`` (per print and pooled) and ``NAME.md`` (``--name``, default
``results``) into ``--out`` and the example figures into ``--figures``;
``--linewidth-noise-um`` runs the twin with another camera noise σ of L_w (default: the
twin's, ``noise.toml``).
"""

from __future__ import annotations

import datetime as _dt
import json
import time
from pathlib import Path

import click
import numpy as np
import pandas as pd

from ajtwin.apps.quality.part_map import Tolerance, part_map_of_record
from ajtwin.apps.quality.report import plot_part_map
from ajtwin.estimation import Twin
from ajtwin.estimation.print_time import program_for_record
from ajtwin.model import load_parameters
from ajtwin.simulation import run_job_print
from ajtwin.simulation.job_print import line_at_print_times

ROOT = Path(__file__).resolve().parents[3]
DEFAULT_PROGRAM = ROOT / "tests" / "data" / "prg" / "prg2svg" / "1-nafbot.prg"
#: the first minutes, where the twin's start (initial fit, first EM) is reported apart
WARM_UP_S = 300.0


def true_line(job_print, points: pd.DataFrame) -> np.ndarray:
    """The true (L_w, L_o) at the sample points' print times and speeds (n, 2)."""
    virtual = job_print.virtual
    last = len(job_print.record) - 1
    return line_at_print_times(
        np.minimum(points["time_s"].to_numpy(dtype=float), last),
        points["speed_mm_s"].to_numpy(dtype=float),
        virtual.states,
        virtual.processes.head_inputs,
        virtual.outputs_true,
        load_parameters(),
        virtual.line_coefficients,
        virtual.machine,
        job_print.line_speed_law,
    )


#: the print's fault-free stretch the tolerance is centred on [s]
TOLERANCE_FROM_S = (1800, 3600)
#: the study's prints: name → (scenario, overrides)
PRINTS = {
    "clog ×50": ("nozzle_clog", None),
    "clog ×300": ("nozzle_clog", {"fault": {"nozzle_deposition_multiplier": 300.0}}),
    "clean": ("exp1", None),
}


def print_tolerance(record, half_width_um: float) -> Tolerance:
    """Target = median true width over 30–60 min, rounded to 0.5 µm; ± half-width."""
    width = record.data["true_linewidth_um"].to_numpy(dtype=float)
    width = width[TOLERANCE_FROM_S[0] : TOLERANCE_FROM_S[1]]
    target = round(float(np.nanmedian(width)) * 2.0) / 2.0
    return Tolerance(target - half_width_um, target + half_width_um)


def judge(part, truth: np.ndarray, onset_s: float | None) -> dict:
    """Flags against the truth per portion, coverage, and what the errors look like."""
    points, table = part.points, part.portions
    tol = part.tolerance
    width = truth[:, 0]
    index = points["portion"].to_numpy()
    outside = pd.Series((width < tol.low_um) | (width > tol.high_um)).groupby(index).max()
    truly = outside.to_numpy(dtype=bool)
    # how far the truth's worst point is beyond (+) or inside (−) the nearest limit
    margin = pd.Series(np.maximum(tol.low_um - width, width - tol.high_um)).groupby(index).max()
    flagged = table["flagged"].to_numpy(dtype=bool)
    start = table["printed_from_s"].to_numpy(dtype=float)
    after = start >= onset_s if onset_s is not None else np.zeros(len(table), dtype=bool)
    wrong = flagged != truly
    counts = {
        "portions": int(len(table)),
        "truly_out": int(truly.sum()),
        "flagged": int(flagged.sum()),
        "both": int((truly & flagged).sum()),
        "after_onset_truly_out": int((truly & after).sum()),
        "after_onset_flagged": int((flagged & after).sum()),
        "after_onset_both": int((truly & flagged & after).sum()),
        "before_onset_truly_out": int((truly & ~after).sum()),
        "before_onset_flagged": int((flagged & ~after).sum()),
        "wrong": int(wrong.sum()),
        "wrong_in_warm_up": int((wrong & (start < WARM_UP_S)).sum()),
        "wrong_median_abs_margin_um": float(np.median(np.abs(margin.to_numpy()[wrong])))
        if wrong.any()
        else None,
    }
    err = width - points["lw_mean_um"].to_numpy(dtype=float)
    sd = points["lw_sd_um"].to_numpy(dtype=float)
    late = points["time_s"].to_numpy(dtype=float) >= WARM_UP_S
    return {
        **counts,
        "coverage": part.coverage_of(width),
        "coverage_after_warm_up": float(
            np.average(np.abs(err[late]) <= 2 * sd[late], weights=points["weight_mm"][late])
        ),
        "lw_error_rms_um": float(np.sqrt(np.mean(err**2))),
        "lw_sd_mean_um": float(np.mean(sd)),
    }


def study_twin(linewidth_noise_um: float | None) -> Twin:
    """The twin the study runs: the default one, or one whose camera noise σ of L_w is
    ``linewidth_noise_um`` (L_o's scaled alike) — to show what the band's width owes to it."""
    twin = Twin.default()
    if linewidth_noise_um is None:
        return twin
    std = list(twin.config.measurement_std)
    std[1] *= linewidth_noise_um / std[0]
    std[0] = linewidth_noise_um
    return Twin.default(measurement_std=tuple(std))


def measure_print(
    program,
    name: str,
    seed: int,
    truth: str,
    half_width: float,
    figure=None,
    linewidth_noise_um: float | None = None,
):
    """One virtual job print (:data:`PRINTS` ``name``) mapped and judged (a dict; the figure
    drawn when asked)."""
    t0 = time.perf_counter()
    scenario, overrides = PRINTS[name]
    job_print = run_job_print(program, scenario, seed, truth_generator=truth, overrides=overrides)
    record = job_print.record
    tolerance = print_tolerance(record, half_width)
    part = part_map_of_record(
        record,
        program_for_record(record, program),
        tolerance,
        twin=study_twin(linewidth_noise_um),
        source=f"{scenario} seed {seed} ({truth})",
    )
    onset = record.meta.get("fault_onset_s") if scenario != "exp1" else None
    result = judge(part, true_line(job_print, part.points), onset)
    if figure is not None:
        plot_part_map(part, figure)
    return {
        "print": name,
        "scenario": scenario,
        "seed": seed,
        "truth": truth,
        "tolerance_um": list(tolerance),
        "onset_s": onset,
        "alarms": part.alarms[["cause", "detected_s", "onset_s"]].to_dict("records"),
        "wall_s": time.perf_counter() - t0,
        **result,
    }


def pooled(rows: list[dict]) -> dict:
    """Precision, recall and coverage over a group of prints."""
    total = {k: sum(r[k] for r in rows) for k in ("truly_out", "flagged", "both",
             "after_onset_truly_out", "after_onset_flagged", "after_onset_both",
             "before_onset_flagged", "before_onset_truly_out", "wrong", "wrong_in_warm_up",
             "portions")}  # fmt: skip

    def ratio(a, b):
        return None if b == 0 else a / b

    return {
        **total,
        "precision": ratio(total["both"], total["flagged"]),
        "recall": ratio(total["both"], total["truly_out"]),
        "after_onset_precision": ratio(total["after_onset_both"], total["after_onset_flagged"]),
        "after_onset_recall": ratio(total["after_onset_both"], total["after_onset_truly_out"]),
        "coverage_min": min(r["coverage"] for r in rows),
        "coverage_mean": float(np.mean([r["coverage"] for r in rows])),
        "coverage_after_warm_up_min": min(r["coverage_after_warm_up"] for r in rows),
    }


def _pct(value) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def markdown_table(result: dict) -> str:
    """The validation table: per group (scenario × generator) and per print."""
    lines = [
        "| prints | portions | truly out | flagged | precision | recall | after onset: "
        "precision / recall | coverage ±2σ (min / mean) | after the first 5 min (min) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, g in result["pooled"].items():
        lines.append(
            f"| {key} | {g['portions']} | {g['truly_out']} | {g['flagged']} | "
            f"{_pct(g['precision'])} | {_pct(g['recall'])} | "
            f"{_pct(g['after_onset_precision'])} / {_pct(g['after_onset_recall'])} | "
            f"{_pct(g['coverage_min'])} / {_pct(g['coverage_mean'])} | "
            f"{_pct(g['coverage_after_warm_up_min'])} |"
        )
    lines += [
        "",
        "| print | tolerance µm | truly out | flagged | both | wrong (in first 5 min) | "
        "median \\|margin\\| of wrong µm | coverage | L_w rms error / mean σ µm |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["prints"]:
        margin = r["wrong_median_abs_margin_um"]
        lines.append(
            f"| {r['print']}, {r['truth']} seed {r['seed']} | "
            f"{r['tolerance_um'][0]:g}–{r['tolerance_um'][1]:g} | {r['truly_out']} | "
            f"{r['flagged']} | {r['both']} | {r['wrong']} ({r['wrong_in_warm_up']}) | "
            f"{'–' if margin is None else f'{margin:.2f}'} | {_pct(r['coverage'])} | "
            f"{r['lw_error_rms_um']:.2f} / {r['lw_sd_mean_um']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


@click.command()
@click.option("--program", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=DEFAULT_PROGRAM, show_default=True)  # fmt: skip
@click.option("--seeds", default="1-4", show_default=True, help="e.g. 1-4 or 1,3,5")
@click.option("--truth", "truths", default="model,alt", show_default=True)
@click.option("--half-width", type=float, default=2.0, show_default=True, help="±µm")
@click.option("--out", type=click.Path(path_type=Path), default=Path("docs/results/part_map"))
@click.option("--figures", type=click.Path(path_type=Path), default=Path("docs/figures/part_map"))
@click.option(
    "--linewidth-noise-um",
    type=float,
    default=None,
    help="Run the twin with this camera noise σ of L_w (default: the twin's, noise.toml).",
)
@click.option("--name", default="results", show_default=True, help="Output file stem.")
def main(program, seeds, truths, half_width, out, figures, linewidth_noise_um, name):
    """Run the study and write NAME.json, NAME.md and the example figures."""
    out.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    rows = []
    for truth in truths.split(","):
        for seed in _seeds(seeds):
            for kind in PRINTS:
                figure = None
                if seed == _seeds(seeds)[0] and truth == "model" and kind != "clean":
                    figure = figures / f"{kind.replace(' ×', '_x')}_seed{seed}.png"
                row = measure_print(
                    program, kind, seed, truth, half_width, figure, linewidth_noise_um
                )
                rows.append(row)
                click.echo(
                    f"{kind} {truth} seed {seed}: flagged {row['flagged']}, truly out "
                    f"{row['truly_out']}, both {row['both']}, coverage {row['coverage']:.3f} "
                    f"({row['wall_s']:.0f} s)",
                    err=True,
                )
    groups = {}
    for row in rows:
        groups.setdefault(f"{row['print']}, {row['truth']} generator", []).append(row)
    result = {
        "program": program.name,
        "measured": _dt.date.today().isoformat(),
        "half_width_um": half_width,
        "linewidth_noise_um": linewidth_noise_um,
        "pooled": {key: pooled(group) for key, group in groups.items()},
        "prints": rows,
    }
    (out / f"{name}.json").write_text(json.dumps(result, indent=1, default=float))
    (out / f"{name}.md").write_text(markdown_table(result))
    click.echo(markdown_table(result))


if __name__ == "__main__":
    main()
