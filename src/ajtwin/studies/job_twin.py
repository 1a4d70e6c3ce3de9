"""The twin on a job: state errors and honest bands on job prints against straight lines.

For each truth generator ("model", the twin's own equations; "alt", the second one that
tuned nothing) and each seed, the same machine and scenario (exp1, 90 min) printed three
ways, each run by the twin with EM (the default ``Twin``), filtered and RTS-smoothed:

* **straight**: the paper's line at 2 mm/s, a camera at the nozzle;
* **job trailing**: each public program (``--programs``, default the prg2svg programs of
  the test data: ``4-naf 654321.prg``, ``1-nafbot.prg``) looped to 90 min as an array of
  parts side by side (pitch 35 × 10 mm), the camera trailing at 5 mm (−5, 0) mm; the twin
  is given the program (``ajtwin estimate --job``): its horizon and the speeds at τ;
* **job inspection**: the same print with no camera during it, and the inspection pass
  after it (the paper's set-up).

Per state (d_a, V_l, ΔR_T, ΔR_N, φ_A) over the print's seconds: RMS error, ±2σ coverage
and rms z = rms((x̂ − x)/σ) (1: honest bands), pooled over the seeds; per seed in the JSON.
With ``--commissioned`` also held-out machines of the second generator commissioned as in
:mod:`ajtwin.studies.machine`, the calibrated twin on their next print (straight, trailing,
inspection).

``python -m ajtwin.studies.job_twin [--seeds 1-5] [--minutes 90] [--commissioned 1001-1003]
[--out docs/results/job_twin]`` writes ``results.json`` and ``summary.md`` there.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ajtwin.engine.commissioning import calibrated_twin, commissioned_start
from ajtwin.estimation.print_time import program_for_record
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.job_print import CameraSettings, JobSettings, run_job_print
from ajtwin.simulation.printer import run_virtual_print
from ajtwin.studies import machine_description
from ajtwin.studies.machine import commission_virtual_machine, print_seed_of

OUT = Path("docs") / "results" / "job_twin"
PROGRAMS_DIR = Path("tests") / "data" / "prg" / "prg2svg"
PROGRAMS = ("4-naf 654321.prg", "1-nafbot.prg")
PITCH_MM = (35.0, 10.0)
OFFSET_MM = (-5.0, 0.0)
STATES = ("d_a", "V_l", "ΔR_T", "ΔR_N", "φ_A")


def state_metrics(run, truth: np.ndarray, n: int, smoothed: bool) -> dict:
    """Per state over the first ``n`` steps: Σ error², Σ inside ±2σ, Σ z², count."""
    src = run.smoothed if smoothed else run.filtered
    means = np.asarray(src.means)[:n]
    stds = np.sqrt(np.maximum(np.diagonal(run._total_cov(src.covariances), 0, 1, 2), 0))[:n]
    error = means - truth[:n]
    z = error / np.maximum(stds, 1e-300)
    return {
        name: {
            "sum_sq_error": float(np.sum(error[:, i] ** 2)),
            "inside_2sigma": int(np.sum(np.abs(z[:, i]) <= 2.0)),
            "sum_sq_z": float(np.sum(z[:, i] ** 2)),
            "count": int(n),
        }
        for i, name in enumerate(STATES)
    }


def _both(run, truth, n) -> dict:
    return {
        "filtered": state_metrics(run, truth, n, False),
        "smoothed": state_metrics(run, truth, n, True),
    }


def job_runs(program: Path, twin_factory, print_kwargs: dict, n: int, start=None) -> dict:
    """The job printed with a trailing camera and with an inspection pass: the twin's
    metrics on each, with the filing counts."""
    out = {}
    for mode in ("trailing", "inspection"):
        camera = CameraSettings(mode=mode, offset_mm=OFFSET_MM if mode == "trailing" else None)
        job_print = run_job_print(
            program,
            camera=camera,
            job_settings=JobSettings(repeat_pitch_mm=PITCH_MM),
            **print_kwargs,
        )
        record = job_print.record
        job = program_for_record(record, program)
        run = twin_factory().run(record, job=job, smooth=True, start=start)
        out[mode] = {
            **_both(run, record.true_states, n),
            "camera": run.camera_counts,
            "rows": len(record),
        }
    return out


def one_seed(generator: str, seed: int, minutes: float, programs) -> dict:
    """Straight line, then every program trailing and inspected: one machine, one seed."""
    n = int(round(minutes * 60))
    straight = run_virtual_print("exp1", seed, minutes, truth_generator=generator).record
    run = Twin.default().run(straight, smooth=True)
    result = {"straight": _both(run, straight.true_states, n)}
    kwargs = dict(scenario="exp1", seed=seed, duration_min=minutes, truth_generator=generator)
    for program in programs:
        result[program.name] = job_runs(program, Twin.default, kwargs, n)
    return result


def one_commissioned(machine_seed: int, minutes: float, programs) -> dict:
    """A held-out machine (second generator) commissioned, then its next print straight and
    as each job, run by the calibrated twin from the commissioned start."""
    n = int(round(minutes * 60))
    print_seed = print_seed_of(machine_seed)
    comm, done, _ = commission_virtual_machine(
        print_seed, "alt", machine_seed=machine_seed, learn_noise_scale=False
    )
    start = commissioned_start(done.result)
    straight = run_virtual_print(
        "exp1", print_seed + 1, minutes, continue_from=comm.record, truth_generator="alt"
    ).record
    run = calibrated_twin(done.result).run(straight, smooth=True, start=start)
    result = {"straight": _both(run, straight.true_states, n), "machine": comm.machine.name}
    kwargs = dict(
        scenario="exp1",
        seed=print_seed + 1,
        duration_min=minutes,
        truth_generator="alt",
        continue_from=comm.record,
    )
    for program in programs:
        result[program.name] = job_runs(
            program, lambda: calibrated_twin(done.result), kwargs, n, start
        )
    return result


def pooled(runs: list[dict]) -> dict:
    """RMS error, ±2σ coverage and rms z per state pooled over runs' :func:`state_metrics`."""
    out = {}
    for name in STATES:
        count = sum(r[name]["count"] for r in runs)
        out[name] = {
            "rms_error": float(np.sqrt(sum(r[name]["sum_sq_error"] for r in runs) / count)),
            "coverage": sum(r[name]["inside_2sigma"] for r in runs) / count,
            "rms_z": float(np.sqrt(sum(r[name]["sum_sq_z"] for r in runs) / count)),
        }
    return out


def summarise(per_seed: list[dict], programs) -> dict:
    """{configuration: {estimator: pooled metrics}} over the seeds of one group."""
    table = {}
    for estimator in ("filtered", "smoothed"):
        table.setdefault("straight", {})[estimator] = pooled(
            [s["straight"][estimator] for s in per_seed]
        )
        for program in programs:
            for mode in ("trailing", "inspection"):
                key = f"{program.name} {mode}"
                table.setdefault(key, {})[estimator] = pooled(
                    [s[program.name][mode][estimator] for s in per_seed]
                )
    return table


UNITS = {"d_a": "µm", "V_l": "mL", "ΔR_T": "µm", "ΔR_N": "µm", "φ_A": ""}


def markdown(results: dict, command: str) -> str:
    """The study's table: per group, configuration and estimator, each state's RMS error,
    ±2σ coverage and rms z."""
    lines = [
        "# The twin on a job print",
        "",
        f"Command: `{command}`  ",
        f"Computer: {results['computer']}; wall {results['wall_s']:.0f} s; "
        f"{results['minutes']:g}-min exp1 prints.",
        "",
        "Each cell: RMS error · ±2σ coverage · rms z (1 = honest bands), pooled over the seeds.",
    ]
    header = "| configuration | estimator | " + " | ".join(
        f"{s} [{UNITS[s]}]" if UNITS[s] else s for s in STATES
    )
    for info in results["groups"].values():
        lines += ["", f"## {info['title']}", "", header + " |"]
        lines.append("|---|---|" + "---|" * len(STATES))
        for config, estimators in info["table"].items():
            for estimator, metrics in estimators.items():
                cells = [
                    f"{m['rms_error']:.3g} · {100 * m['coverage']:.0f} % · {m['rms_z']:.2f}"
                    for m in (metrics[s] for s in STATES)
                ]
                lines.append(f"| {config} | {estimator} | " + " | ".join(cells) + " |")
        camera = info.get("camera")
        if camera:
            lines += ["", "Camera frames filed at their print times (summed over seeds):"]
            for key, counts in camera.items():
                dropped = sum(v for k, v in counts.items() if k.startswith("dropped_"))
                lines.append(f"- {key}: {counts['filed']} filed, {dropped} dropped")
    return "\n".join(lines) + "\n"


def _camera_totals(per_seed: list[dict], programs) -> dict:
    totals = {}
    for s in per_seed:
        for program in programs:
            for mode in ("trailing", "inspection"):
                counts = s[program.name][mode]["camera"]
                key = f"{program.name} {mode}"
                into = totals.setdefault(key, {})
                for k, v in counts.items():
                    if k != "horizon_s":
                        into[k] = into.get(k, 0) + v
    return totals


def run_all(seeds, minutes, programs, commissioned=(), progress=print, checkpoint=None) -> dict:
    """Every group (both generators over ``seeds``; commissioned held-out machines)."""
    t0 = time.perf_counter()
    results = {"minutes": minutes, "computer": machine_description(), "groups": {}, "raw": {}}
    titles = {
        "model": "First truth generator (the twin's own equations)",
        "alt": "Second truth generator (evaluation; tuned nothing)",
        "commissioned": "Commissioned held-out machines (second generator, calibrated twin)",
    }
    plan = [(g, list(seeds)) for g in ("model", "alt")]
    if commissioned:
        plan.append(("commissioned", list(commissioned)))
    for group, keys in plan:
        per_seed = []
        for key in keys:
            if group == "commissioned":
                per_seed.append(one_commissioned(key, minutes, programs))
            else:
                per_seed.append(one_seed(group, key, minutes, programs))
            progress(f"{group} {key} done ({time.perf_counter() - t0:.0f} s)")
            results["raw"][group] = per_seed
            if checkpoint is not None:
                checkpoint(results)
        results["groups"][group] = {
            "title": titles[group] + f", seeds {keys[0]}–{keys[-1]}",
            "table": summarise(per_seed, programs),
            "camera": _camera_totals(per_seed, programs),
        }
    results["wall_s"] = time.perf_counter() - t0
    return results


def _range(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def _option(argv, name, default):
    return argv[argv.index(name) + 1] if name in argv else default


if __name__ == "__main__":
    argv = sys.argv[1:]
    seeds = _range(_option(argv, "--seeds", "1-5"))
    minutes = float(_option(argv, "--minutes", "90"))
    commissioned = _range(_option(argv, "--commissioned", "")) if "--commissioned" in argv else []
    out = Path(_option(argv, "--out", str(OUT)))
    folder = Path(_option(argv, "--programs", str(PROGRAMS_DIR)))
    programs = [folder / name for name in PROGRAMS]
    out.mkdir(parents=True, exist_ok=True)

    def checkpoint(partial):
        (out / "results.partial.json").write_text(json.dumps(partial, indent=1, default=float))

    results = run_all(seeds, minutes, programs, commissioned, checkpoint=checkpoint)
    (out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    (out / "results.partial.json").unlink(missing_ok=True)
    command = "python -m ajtwin.studies.job_twin " + " ".join(argv)
    text = markdown(results, command.strip())
    (out / "summary.md").write_text(text)
    print(text)
