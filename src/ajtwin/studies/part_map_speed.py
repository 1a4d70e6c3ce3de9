"""The part map's band on a print at speeds away from ν_ref, with and without the speed law
learnt from the camera.

A held-out CAM-style program (``tests/data/prg/other_style.prg``: upper-case ACSPL+, an
outline of lines and an arc at the process speed 3 mm/s, a bar at ``VEL(X)=5``) printed by
the second truth generator (whose speed law is not a power law) with the packaged nozzle
clog is mapped twice by the same twin: with the packaged speed law (σ_b the bracket) and
with the exponents learnt from the print's own camera readings
(:mod:`ajtwin.estimation.line_speed_fit`). Each map is judged against the true line as
:mod:`ajtwin.studies.part_map` judges it (a portion truly out where the true width leaves
the tolerance anywhere along it; precision, recall, overall and after the fault's onset;
coverage of the ±2σ band), and the band's width (4σ of L_w over the sample points) is
reported.

    python -m ajtwin.studies.part_map_speed [--seed 9] [--truth alt] [--tolerance 68+-2.5] \\
        [--out docs/results/part_map/speed_law.json]
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from ajtwin.apps.quality.part_map import parse_tolerance, part_map_of_record
from ajtwin.estimation import Twin
from ajtwin.estimation.print_time import program_for_record
from ajtwin.simulation import run_job_print
from ajtwin.studies.part_map import judge, pooled, true_line

ROOT = Path(__file__).resolve().parents[3]
DEFAULT_PROGRAM = ROOT / "tests" / "data" / "prg" / "other_style.prg"


def band_figures(part) -> dict:
    """Width of the ±2σ band of L_w over the sample points [µm]: min, median, max."""
    width = 4.0 * part.points["lw_sd_um"].to_numpy(dtype=float)
    return {
        "band_width_min_um": float(width.min()),
        "band_width_median_um": float(np.median(width)),
        "band_width_max_um": float(width.max()),
    }


def measure(program, scenario: str, seed: int, truth: str, tolerance, learn: bool) -> dict:
    """One map of the print (learnt speed law or not), judged."""
    job_print = run_job_print(program, scenario, seed, truth_generator=truth)
    record = job_print.record
    part = part_map_of_record(
        record,
        program_for_record(record, program),
        tolerance,
        twin=Twin.default(),
        learn_speed=learn,
    )
    onset = record.meta.get("fault_onset_s")
    result = judge(part, true_line(job_print, part.points), onset)
    summary = pooled([result])
    return {
        "speed_law": "learnt from the camera" if learn else "packaged",
        "exponents": part.speed_exponents.to_dict(),
        "true_speed_law": record.meta.get("truth_draws", {}).get("line_speed"),
        **band_figures(part),
        **{
            k: summary[k]
            for k in ("precision", "recall", "after_onset_precision", "after_onset_recall")
        },  # fmt: skip
        **result,
    }


@click.command()
@click.option("--program", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=DEFAULT_PROGRAM, show_default=True)  # fmt: skip
@click.option("--scenario", default="nozzle_clog", show_default=True)
@click.option("--seed", type=int, default=9, show_default=True)
@click.option("--truth", default="alt", show_default=True)
@click.option("--tolerance", default="68+-2.5", show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="JSON file")
def main(program, scenario, seed, truth, tolerance, out):
    """Map the print with the packaged and with the learnt speed law; print both."""
    tol = parse_tolerance(tolerance)
    rows = [measure(program, scenario, seed, truth, tol, learn) for learn in (False, True)]
    for r in rows:
        click.echo(
            f"{r['speed_law']}: b = {r['exponents']['linewidth_exponent']:.3f} ± "
            f"{r['exponents']['linewidth_exponent_std']:.3f}; band ±2σ "
            f"{r['band_width_min_um']:.1f}–{r['band_width_max_um']:.1f} µm (median "
            f"{r['band_width_median_um']:.1f}); flagged {r['flagged']} of {r['portions']}, "
            f"truly out {r['truly_out']}; precision {r['precision']:.2f}, recall "
            f"{r['recall']:.2f}; after onset {r['after_onset_precision']:.2f} / "
            f"{r['after_onset_recall']:.2f}; coverage {r['coverage']:.3f}"
        )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        command = (
            f"python -m ajtwin.studies.part_map_speed --scenario {scenario} --seed {seed} "
            f"--truth {truth} --tolerance {tolerance}"
        )
        payload = {"program": program.name, "command": command, "maps": rows}
        out.write_text(json.dumps(payload, indent=1, default=float))


if __name__ == "__main__":
    main()
