"""The control study: every strategy × drift scenario × seed in closed loop with the
virtual printer (``ajtwin control simulate``), the runs' metrics merged into one table
(``ajtwin control merge``) and a figure per scenario.

Run through its commands, ``ajtwin control simulate`` and ``ajtwin control merge``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from ajtwin.apps.planning.closed_loop import STRATEGIES
from ajtwin.apps.planning.mpc import ControlSettings
from ajtwin.apps.planning.strategies import start_inputs
from ajtwin.estimation.twin import Twin
from ajtwin.io.records import write_record
from ajtwin.job import SpeedSchedule
from ajtwin.model.names import INPUT_NAMES
from ajtwin.simulation.job_print import CameraSettings, read_job
from ajtwin.studies.closed_loop import ClosedLoopPlan, simulate_strategy

#: the drift scenarios of the comparison; slow_clog ships with the controller
DRIFT_SCENARIOS = ("exp1", "clean_long", "ink_running_low", "slow_clog")


@dataclass(frozen=True)
class JobSetup:
    """A job print for the comparison: the program read with its speeds, the camera, the
    looping.

    Attributes
    ----------
    job : ajtwin.job.Job
        The program as read (with its speeds per layer, stroke or feature), not looped.
    camera : CameraSettings
    repeat_pitch_mm : (float, float) or None
        Runs of the loop side by side at this pitch; None: over each other.
    """

    job: object
    camera: CameraSettings
    repeat_pitch_mm: tuple | None = None

    @classmethod
    def read(cls, program, process_speed=None, camera_mode=None, offset_mm=None, pitch_mm=None):
        """From the command's options: ``process_speed`` one speed [mm/s] or a
        :class:`~ajtwin.job.SpeedSchedule`; a camera offset of (0, 0) without a mode is the
        camera at the nozzle."""
        schedule = process_speed if isinstance(process_speed, SpeedSchedule) else None
        speed = None if schedule is not None else process_speed
        job, _ = read_job(program, speed, None, schedule)
        if camera_mode is None and offset_mm is not None and not any(offset_mm):
            camera_mode = "at_nozzle"
        camera = CameraSettings(mode=camera_mode, offset_mm=offset_mm)
        pitch = None if pitch_mm is None else tuple(float(v) for v in pitch_mm)
        return cls(job, camera, pitch)

    def meta(self) -> dict:
        """What the comparison's metrics.json says of the job print."""
        schedule = self.job.speed_schedule
        return {
            "program": Path(self.job.path).name,
            "process_speeds": None if schedule is None else schedule.describe(),
            "camera": self.camera.meta(),
            "repeat_pitch_mm": None if self.repeat_pitch_mm is None else list(self.repeat_pitch_mm),
        }

    def kwargs(self) -> dict:
        """Fields of :class:`ajtwin.studies.closed_loop.ClosedLoopPlan`."""
        return {"job": self.job, "camera": self.camera, "repeat_pitch_mm": self.repeat_pitch_mm}


@dataclass(frozen=True)
class ComparisonGrid:
    """The prints a comparison runs: every strategy on every scenario and seed, each aiming
    at one target linewidth.

    Attributes
    ----------
    scenarios : tuple of str or Path
        The drift scenarios: packaged names, the controller's own (``slow_clog``) or files.
    seeds : tuple of int
        The prints' seeds; every scenario runs each.
    target_um : float
        Target linewidth L_w [µm].
    strategies : tuple of str
        The strategies compared (default all of
        :data:`~ajtwin.apps.planning.closed_loop.STRATEGIES`).
    duration_min : float, optional
        Length of every print [min] (default: each scenario's own).

    Examples
    --------
    >>> ComparisonGrid(["exp1"], range(1, 3), 55.0).seeds
    (1, 2)
    """

    scenarios: tuple
    seeds: tuple
    target_um: float
    strategies: tuple = STRATEGIES
    duration_min: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "scenarios", tuple(self.scenarios))
        object.__setattr__(self, "seeds", tuple(int(s) for s in self.seeds))
        object.__setattr__(self, "strategies", tuple(self.strategies))


def compare(
    grid: ComparisonGrid,
    out_dir,
    *,
    settings=None,
    limits=None,
    max_overspray_um=None,
    progress=None,
    log=print,
    truth: str = "model",
    job: JobSetup | None = None,
) -> dict:
    """Run every strategy on every scenario and seed of ``grid``; write records, metrics
    and figures.

    ``job``: every print runs this program under its camera (:class:`JobSetup`); the
    metrics are then per printed length.
    """
    target_um, strategies, duration_min = grid.target_um, grid.strategies, grid.duration_min
    settings = settings or ControlSettings.load()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    twin = Twin.default()
    u0, reach = start_inputs(twin, target_um, limits, max_overspray_um)
    log(
        f"target {target_um:g} µm (reachable on the nominal model {reach[0]:.1f}–{reach[1]:.1f}"
        f" µm); start inputs I_A {u0[0]:.1f} mA, Q_c {u0[1]:.2f} sccm, Q_s {u0[2]:.2f} sccm"
    )
    results = {
        "target_linewidth_um": float(target_um),
        "reachable_nominal_um": list(reach),
        "start_inputs": u0.tolist(),
        "settings": settings.source,
        "strategies": list(strategies),
        "seeds": list(grid.seeds),
        "duration_min": duration_min,
        "truth_generator": truth,
        # control.toml's tuning was chosen on the first generator (exp1 seeds 0 and 6)
        "tuned_on": "model (first generator): exp1 seeds 0 and 6",
        "job": None if job is None else job.meta(),
        "scenarios": {},
    }
    metrics_path = out / "metrics.json"
    options = {
        "duration_min": duration_min,
        "settings": settings,
        "limits": limits,
        "max_overspray_um": max_overspray_um,
        "u0": u0,
        "progress": progress,
        "truth": truth,
        **({} if job is None else job.kwargs()),
    }
    for scenario in grid.scenarios:
        runs = {}
        per_seed = {}
        for seed in grid.seeds:
            name, runs[int(seed)] = run_seed(
                scenario, seed, strategies, target_um, out, options, log=log
            )
            per_seed[str(seed)] = {k: r.metrics for k, r in runs[int(seed)].items()}
        summary = summarise(per_seed, strategies)
        results["scenarios"][name] = {"per_seed": per_seed, "summary": summary}
        first = min(runs)
        plot_scenario(runs[first], target_um, out / f"{name}.png", f"{name}, seed {first}")
        # written after each scenario: nothing lost if a later one fails or is killed
        metrics_path.write_text(json.dumps(results, indent=2))
    return results


def run_seed(scenario, seed, strategies, target_um, records_dir, options, log=print):
    """Every strategy on one print (scenario, seed): each run's record and commands written
    to ``records_dir/<scenario>/seed<N>/``. Returns (the scenario's name, {strategy: run}).

    ``options``: fields of :class:`ajtwin.studies.closed_loop.ClosedLoopPlan` (and
    ``progress``).
    """
    runs = {}
    name = str(scenario)
    for strategy in strategies:
        t0, wall0 = time.process_time(), time.perf_counter()
        fields = {k: v for k, v in options.items() if k != "progress"}
        plan = ClosedLoopPlan(scenario, int(seed), target_um, **fields)
        run = simulate_strategy(plan, strategy, progress=options.get("progress"))
        name = run.scenario
        stem = Path(records_dir) / name / f"seed{seed}"
        write_record(run.record, stem / f"{strategy}.parquet")
        run.commands.to_csv(stem / f"{strategy}_commands.csv", index=False)
        runs[strategy] = run
        m = run.metrics
        log(
            f"{name} seed {seed} {strategy}: rms {m['rms_error_um']:.2f} µm, "
            f"within ±2 µm {m['within_2um_fraction']:.0%}, holds {m['n_holds']}, "
            f"{time.process_time() - t0:.0f} s CPU, {time.perf_counter() - wall0:.0f} s wall"
        )
    return name, runs


def summarise(per_seed: dict, strategies) -> dict:
    """Mean over seeds per strategy, and the ratios the issue asks for."""
    out = {}
    for strategy in strategies:
        rows = [seed[strategy] for seed in per_seed.values() if strategy in seed]
        if not rows:
            continue
        rms = np.array([r["rms_error_um"] for r in rows])
        solve = [r["solve_ms_mean"] for r in rows if r["solve_ms_mean"] is not None]
        solve_max = [r["solve_ms_max"] for r in rows if r["solve_ms_max"] is not None]
        out[strategy] = {
            "rms_error_um_mean": float(rms.mean()),
            "rms_error_um_per_seed": rms.tolist(),
            "within_2um_fraction_mean": float(np.mean([r["within_2um_fraction"] for r in rows])),
            "mean_overspray_um": float(np.mean([r["mean_overspray_um"] for r in rows])),
            "input_travel_mean": {
                n: float(np.mean([r["input_travel"][n] for r in rows])) for n in INPUT_NAMES
            },
            "solve_ms_mean": float(np.mean(solve)) if solve else None,
            "solve_ms_max": float(np.max(solve_max)) if solve_max else None,
            **_wall_solve(rows),
            "holds_mean": float(np.mean([r["n_holds"] for r in rows])),
            "ink_stop_s_per_seed": [r.get("ink_stop_s") for r in rows],
            "all_inside_limits": bool(all(r["inside_limits"] for r in rows)),
            "all_rate_limits_respected": bool(all(r["rate_limits_respected"] for r in rows)),
        }
    if "mpc_twin" in out:
        twin_rms = out["mpc_twin"]["rms_error_um_mean"]
        for other in ("open_loop", "pi", "mpc_nominal"):
            if other in out and twin_rms > 0:
                out[f"ratio_rms_{other}_over_mpc_twin"] = out[other]["rms_error_um_mean"] / twin_rms
    return out


def _wall_solve(rows) -> dict:
    """Wall-clock solve times over the seeds' runs (those that recorded them)."""
    mean = [r["solve_wall_ms_mean"] for r in rows if r.get("solve_wall_ms_mean") is not None]
    p95 = [r["solve_wall_ms_p95"] for r in rows if r.get("solve_wall_ms_p95") is not None]
    top = [r["solve_wall_ms_max"] for r in rows if r.get("solve_wall_ms_max") is not None]
    return {
        "solve_wall_ms_mean": float(np.mean(mean)) if mean else None,
        "solve_wall_ms_p95_max": float(np.max(p95)) if p95 else None,
        "solve_wall_ms_max": float(np.max(top)) if top else None,
    }


#: what every merged run must share (else the rows are not comparable)
_MERGE_KEYS = ("target_linewidth_um", "start_inputs", "settings")


def _load_metrics(path) -> tuple[Path, dict]:
    path = Path(path)
    file = path / "metrics.json" if path.is_dir() else path
    if not file.is_file():
        raise FileNotFoundError(f"{path}: no metrics.json (a DIR of ajtwin control simulate)")
    try:
        data = json.loads(file.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(data, dict) or "scenarios" not in data:
        raise ValueError(f"{file}: not a metrics.json of ajtwin control simulate")
    return file, data


def merge_results(paths) -> dict:
    """One metrics table from several ``control simulate`` runs (per seed or scenario).

    Per-seed rows are collected under ``scenario`` (``scenario@alt`` for the second truth
    generator) and the summaries recomputed over every seed found. The runs must share
    the target, the start inputs and the settings; the same scenario, seed and strategy
    twice must agree to the last digit (a re-run of the same thing), else it is an error.
    """
    if not paths:
        raise ValueError("nothing to merge: give one or more run directories")
    merged: dict = {"merged_from": [], "scenarios": {}}
    per_seed: dict = {}
    for path in paths:
        file, data = _load_metrics(path)
        # the run's folder name (regenerate.sh names one per scenario and generator)
        merged["merged_from"].append(file.parent.name or str(file))
        if data.get("note"):
            merged.setdefault("notes", {})[file.parent.name or str(file)] = data["note"]
        for key in _MERGE_KEYS:
            if key not in merged:
                merged[key] = data.get(key)
            elif data.get(key) != merged[key]:
                raise ValueError(
                    f"{file}: {key} = {data.get(key)!r} differs from the runs before "
                    f"({merged[key]!r}); runs with different {key} are not one table"
                )
        truth = data.get("truth_generator", "model")
        merged.setdefault("tuned_on", data.get("tuned_on"))
        for name, block in data["scenarios"].items():
            key = name if truth == "model" else f"{name}@{truth}"
            rows = per_seed.setdefault(key, {})
            for seed, strategies in block["per_seed"].items():
                for strategy, metrics in strategies.items():
                    old = rows.get(seed, {}).get(strategy)
                    if old is not None and old != metrics:
                        raise ValueError(
                            f"{file}: {key} seed {seed} {strategy} differs from an earlier "
                            "run of the same print; merge runs of different prints only"
                        )
                    rows.setdefault(seed, {})[strategy] = metrics
    for key, rows in per_seed.items():
        strategies = [s for s in STRATEGIES if any(s in r for r in rows.values())]
        ordered = dict(sorted(rows.items(), key=lambda kv: int(kv[0])))
        merged["scenarios"][key] = {
            "per_seed": ordered,
            "summary": summarise(ordered, strategies),
        }
    return merged


def metrics_table(results: dict) -> str:
    """The comparison as a Markdown table: RMS error and time within ±2 µm per strategy."""
    lines = [
        "| scenario | seeds | " + " | ".join(STRATEGIES) + " | open/twin | PI/twin | twin stops |",
        "|---" * (len(STRATEGIES) + 5) + "|",
    ]
    for name, block in results["scenarios"].items():
        summary = block["summary"]
        cells = []
        for strategy in STRATEGIES:
            row = summary.get(strategy)
            cells.append(
                "–"
                if row is None
                else f"{row['rms_error_um_mean']:.2f} µm, {row['within_2um_fraction_mean']:.0%}"
            )
        ratios = [summary.get(f"ratio_rms_{other}_over_mpc_twin") for other in ("open_loop", "pi")]
        stops = (summary.get("mpc_twin") or {}).get("ink_stop_s_per_seed") or []
        stop_text = ", ".join("–" if t is None else f"{t / 60:.0f} min" for t in stops)
        lines.append(
            f"| {name} | {','.join(block['per_seed'])} | "
            + " | ".join(cells)
            + " | "
            + " | ".join("–" if r is None else f"{r:.2f}×" for r in ratios)
            + f" | {stop_text or '–'} |"
        )
    return "\n".join(lines) + "\n"


def plot_scenario(runs: dict, target_um: float, path, title: str):
    """The strategies' true L_w (with the ±2 µm band), L_o and set-points, one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(5, 1, figsize=(9, 11), sharex=True)
    colours = {
        "open_loop": "0.4",
        "pi": "tab:orange",
        "mpc_nominal": "tab:green",
        "mpc_twin": "tab:blue",
    }
    speed = None
    for strategy, run in runs.items():
        t = np.arange(len(run.true_outputs)) / 60.0
        colour = colours.get(strategy)
        label = f"{strategy} (rms {run.metrics['rms_error_um']:.2f} µm)"
        line = run.true_outputs[:, :2] if run.true_line is None else run.true_line.copy()
        if run.printed_length is not None:
            line[np.asarray(run.printed_length) <= 0] = np.nan  # nothing printed then
        axes[0].plot(t, line[:, 0], lw=1, color=colour, label=label)
        axes[1].plot(t, line[:, 1], lw=1, color=colour)
        if getattr(run.record, "has_job", False) and speed is None:
            speed = np.where(run.record.shutter_open > 0, run.record.platen_speed, np.nan)
            twin_axis = axes[0].twinx()
            twin_axis.plot(t, speed, lw=0.6, color="0.6", drawstyle="steps-post")
            twin_axis.set_ylabel("printing speed [mm/s]", color="0.5")
        for i in range(3):
            axes[2 + i].plot(t, run.setpoints[:, i], lw=1, color=colour)
        holds = run.commands[run.commands["status"] == "hold"]
        stops = run.commands[run.commands["status"] == "stop"]
        if strategy == "mpc_twin" and len(stops):
            for ax in axes:
                ax.axvline(stops["time_s"].iloc[0] / 60.0, color="tab:red", lw=0.8, ls=":")
            axes[0].annotate(
                "mpc_twin stops: ink low",
                (stops["time_s"].iloc[0] / 60.0, target_um - 2.0),
                fontsize=7,
                color="tab:red",
                ha="right",
                va="top",
            )
        if strategy == "mpc_twin" and len(holds):
            axes[0].plot(
                holds["time_s"] / 60.0,
                np.full(len(holds), target_um),
                "|",
                color="tab:red",
                ms=8,
                label="mpc_twin holds",
            )
    axes[0].axhspan(target_um - 2, target_um + 2, color="tab:blue", alpha=0.08)
    axes[0].axhline(target_um, color="k", lw=0.8, ls="--", label="target")
    axes[0].set_ylabel("true L_w printed [µm]")
    axes[0].legend(fontsize=7, loc="best")
    axes[1].set_ylabel("true L_o printed [µm]")
    for ax, label in zip(axes[2:], ("I_A [mA]", "Q_c [sccm]", "Q_s [sccm]")):
        ax.set_ylabel(label)
    axes[-1].set_xlabel("time [min]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- #
# The PI baseline's tuning on job prints
# --------------------------------------------------------------------------- #

#: PI's grid: closed-loop times τ_c [s] and the share of the camera's median delay taken
#: as SIMC's dead time (0: the loop acts as if it saw the line as printed)
PI_CLOSED_LOOP_TIMES_S = (10.0, 20.0, 40.0, 80.0, 160.0)
PI_DELAY_FRACTIONS = (0.0, 0.25, 0.5, 1.0)
#: the tuning prints: exp1 on the first generator, seeds that are not the comparison's
PI_TUNING_SEEDS = (0, 6)


def tune_pi(
    cameras: dict,
    *,
    seeds=PI_TUNING_SEEDS,
    minutes: float = 45.0,
    target_um: float = 55.0,
    closed_loop_times=PI_CLOSED_LOOP_TIMES_S,
    delay_fractions=PI_DELAY_FRACTIONS,
    scenario: str = "exp1",
    log=print,
) -> dict:
    """The PI baseline tuned fairly for each camera: every (τ_c, delay share) of the grid on
    the tuning prints, the RMS width error per printed length of each, and the best.

    Parameters
    ----------
    cameras : dict
        {name: :class:`JobSetup`}: the same program and speeds under each camera.
    seeds, minutes, target_um, scenario
        The tuning prints (first truth generator; seeds apart from the comparison's 1–5).
    closed_loop_times, delay_fractions
        The grid (:data:`PI_CLOSED_LOOP_TIMES_S`, :data:`PI_DELAY_FRACTIONS`).

    Returns
    -------
    dict
        Per camera: ``grid`` (rows of τ_c, delay share, RMS per seed and mean)
        and ``best`` (the row of least mean RMS).
    """
    settings = ControlSettings.load()
    u0, _ = start_inputs(Twin.default(), target_um)
    out = {
        "scenario": scenario,
        "seeds": [int(s) for s in seeds],
        "minutes": float(minutes),
        "target_linewidth_um": float(target_um),
        "cameras": {},
    }
    for name, setup in cameras.items():
        rows = []
        for tau_c in closed_loop_times:
            for fraction in delay_fractions:
                if setup.camera.mode == "at_nozzle" and fraction != delay_fractions[0]:
                    continue  # no delay to share
                rms = []
                for seed in seeds:
                    plan = ClosedLoopPlan(
                        scenario,
                        int(seed),
                        target_um,
                        duration_min=minutes,
                        settings=settings,
                        u0=u0,
                        controller_options={
                            "closed_loop_time_s": tau_c,
                            "delay_fraction": fraction,
                        },
                        **setup.kwargs(),
                    )
                    run = simulate_strategy(plan, "pi")
                    rms.append(run.metrics["rms_error_um"])
                row = {
                    "closed_loop_time_s": float(tau_c),
                    "delay_fraction": float(fraction),
                    "rms_error_um_per_seed": rms,
                    "rms_error_um_mean": float(np.mean(rms)),
                }
                rows.append(row)
                log(f"{name}: tau_c {tau_c:g} s, delay share {fraction:g}: {np.mean(rms):.3f} µm")
        best = min(rows, key=lambda r: r["rms_error_um_mean"])
        out["cameras"][name] = {"job": setup.meta(), "grid": rows, "best": best}
        log(
            f"{name}: best tau_c {best['closed_loop_time_s']:g} s, delay share "
            f"{best['delay_fraction']:g} (rms {best['rms_error_um_mean']:.3f} µm)"
        )
    return out


# --------------------------------------------------------------------------- #
# The job-print comparison: scenarios × cameras × truth generators × seeds
# --------------------------------------------------------------------------- #

#: The scenarios of the job-print comparison (drift, a slow clog, the ink running low)
JOB_SCENARIOS = ("exp1", "slow_clog", "ink_running_low")


def cameras_from_offsets(text: str, program, process_speed=None, pitch_mm=None) -> dict:
    """``0,5,20,inspection`` → {name: :class:`JobSetup`}: 0 the camera at the nozzle, D a
    camera trailing D mm behind the nozzle along −x (where the public programs' fills come
    from: they advance along +x), ``inspection`` a pass after the print only."""
    cameras = {}
    for part in (p.strip() for p in str(text).split(",") if p.strip()):
        if part == "inspection":
            cameras[part] = JobSetup.read(program, process_speed, "inspection", None, pitch_mm)
            continue
        distance = float(part)
        if not (np.isfinite(distance) and distance >= 0):
            raise ValueError(f"camera offset {part!r}: a distance ≥ 0 mm, or 'inspection'")
        if distance == 0:
            cameras["offset 0 mm"] = JobSetup.read(
                program, process_speed, "at_nozzle", None, pitch_mm
            )
        else:
            cameras[f"offset {distance:g} mm"] = JobSetup.read(
                program, process_speed, "trailing", (-distance, 0.0), pitch_mm
            )
    if not cameras:
        raise ValueError(f"no camera in {text!r}")
    return cameras


def comparison_tasks(cells, seeds, core) -> list:
    """The order the job-print comparison runs its prints in: the ``core`` cells (those
    the aims are judged on) get every seed first, seed by seed; then the others, one seed
    of every cell before the next seed. A comparison cut short by its stop time has thus
    the most seeds where the aims are judged and at least as many seeds on an earlier cell
    as on a later one elsewhere.

    Parameters
    ----------
    cells : list of (truth, camera, scenario)
        In the order of preference.
    seeds : list of int
    core : callable
        ``core(cell)``: whether the cell is one of the core.

    Returns
    -------
    list of (truth, camera, scenario, seed)
    """
    first = [c for c in cells if core(c)]
    rest = [c for c in cells if not core(c)]
    return [(*c, s) for group in (first, rest) for s in seeds for c in group]


#: what a resumed comparison must share with the one in its folder
_RESUME_KEYS = ("target_linewidth_um", "start_inputs", "settings", "strategies", "minutes", "jobs")


def _resumed(path: Path, merged: dict, log=print) -> dict:
    """The cells of an earlier comparison at ``path`` (empty when there is none); an error
    when it is not the same comparison."""
    if not path.is_file():
        return {}
    earlier = json.loads(path.read_text())
    for key in _RESUME_KEYS:
        if json.loads(json.dumps(merged[key])) != earlier.get(key):
            raise ValueError(f"{path}: {key} differs; resume only the same comparison")
    n = sum(
        len(cell["per_seed"])
        for truths in earlier["cameras"].values()
        for block in truths.values()
        for cell in block["scenarios"].values()
    )
    log(f"resuming {path}: {n} prints kept")
    return earlier["cameras"]


def _in_core(cell, scenarios=None, cameras=None) -> bool:
    """Whether a (truth, camera, scenario) cell is one of the core (None: all)."""
    return (scenarios is None or cell[2] in scenarios) and (cameras is None or cell[1] in cameras)


def job_comparison(
    cameras: dict,
    grid: ComparisonGrid,
    out_dir,
    *,
    truths=("model", "alt"),
    core_scenarios=None,
    core_cameras=None,
    stop_at: float | None = None,
    records_dir=None,
    resume: bool = False,
    log=print,
) -> dict:
    """Every strategy on every scenario and seed of ``grid``, under every camera and truth
    generator, merged into one table: ``out_dir/metrics.json`` and ``metrics.md``
    (rewritten after every print), a figure per core cell in ``out_dir``; the records under
    ``records_dir/<truth>/<camera>/<scenario>/seed<N>/`` (default ``out_dir``).

    The prints run in the order of :func:`comparison_tasks`: the core cells
    (``core_scenarios`` × ``core_cameras``, default all) every seed first. ``stop_at``
    (a :func:`time.time`): no print starts that would not end by then at the pace of the
    slowest so far; the table says which seeds ran in each cell. ``resume``: the prints of
    an earlier ``out_dir/metrics.json`` of the same comparison are kept, not run again.
    """
    target_um, strategies, minutes = grid.target_um, grid.strategies, grid.duration_min
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    records = Path(records_dir) if records_dir is not None else out
    settings = ControlSettings.load()
    u0, reach = start_inputs(Twin.default(), target_um)
    merged = {
        "target_linewidth_um": float(target_um),
        "reachable_nominal_um": list(reach),
        "start_inputs": u0.tolist(),
        "settings": settings.source,
        "strategies": list(strategies),
        "truths": list(truths),
        "seeds_asked": list(grid.seeds),
        "minutes": minutes,
        "core": {"scenarios": core_scenarios, "cameras": core_cameras},
        "jobs": {name: setup.meta() for name, setup in cameras.items()},
        "runnable_processes_1min_start": list(os.getloadavg()),
        "cameras": {},
    }
    cells = [(t, c, sc) for c in cameras for sc in grid.scenarios for t in truths]
    core = functools.partial(_in_core, scenarios=core_scenarios, cameras=core_cameras)
    tasks = comparison_tasks(cells, list(grid.seeds), core)
    merged["cameras"] = _resumed(out / "metrics.json", merged, log) if resume else {}
    slowest, done = 0.0, 0
    for truth, camera, scenario, seed in tasks:
        cell = merged["cameras"].get(camera, {}).get(truth, {}).get("scenarios", {})
        if str(seed) in cell.get(scenario, {}).get("per_seed", {}):
            done += 1  # in the table already (resumed)
            continue
        if stop_at is not None and time.time() + slowest > stop_at:
            log(f"stop time reached: {done} of {len(tasks)} prints ran")
            break
        wall0 = time.time()
        options = {"duration_min": minutes, "settings": settings, "u0": u0, "truth": truth}
        folder = records / truth / camera.replace(" ", "_")
        log(f"--- {camera}, truth {truth}, {scenario}, seed {seed} ---")
        name, runs = run_seed(
            scenario,
            seed,
            strategies,
            target_um,
            folder,
            {**options, **cameras[camera].kwargs()},
            log=log,
        )
        slowest, done = max(slowest, time.time() - wall0), done + 1
        block = merged["cameras"].setdefault(camera, {}).setdefault(truth, {"scenarios": {}})
        cell = block["scenarios"].setdefault(name, {"per_seed": {}})
        cell["per_seed"][str(seed)] = {k: r.metrics for k, r in runs.items()}
        cell["summary"] = summarise(cell["per_seed"], strategies)
        if core((truth, camera, scenario)) and len(cell["per_seed"]) == 1:
            title = f"{name}, {camera}, {'first' if truth == 'model' else 'second'} generator"
            stem = f"{name}_{camera.replace(' ', '_')}_{truth}_seed{seed}.png"
            plot_scenario(runs, target_um, out / stem, f"{title}, seed {seed}")
        merged.update(prints_done=done, prints_planned=len(tasks))
        merged["runnable_processes_1min_end"] = list(os.getloadavg())
        (out / "metrics.json").write_text(json.dumps(merged, indent=2))
        (out / "metrics.md").write_text(job_metrics_table(merged))
    return merged


def _cell(row: dict | None, key: str, fmt: str) -> str:
    if row is None or row.get(key) is None:
        return "–"
    return format(row[key], fmt)


def job_metrics_table(merged: dict) -> str:
    """The job-print comparison as Markdown: per scenario, camera and generator the RMS
    width error per printed length of each strategy (and the share within ±2 µm), the
    ratios to the MPC on the twin, overspray, input travel, holds and solve times."""
    head = (
        "| scenario | camera | generator | seeds | open loop | PI | MPC nominal | MPC twin | "
        "open/twin | PI/twin | L_o twin / PI [µm] | travel twin: I_A, Q_c, Q_s | "
        "holds twin | limits twin | solve twin CPU mean/max, wall mean/max [ms] |"
    )
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for camera, by_truth in merged["cameras"].items():
        for truth, result in by_truth.items():
            for scenario, block in result["scenarios"].items():
                s = block["summary"]
                cells = []
                for strategy in STRATEGIES:
                    row = s.get(strategy)
                    cells.append(
                        "–"
                        if row is None
                        else f"{row['rms_error_um_mean']:.2f} µm, "
                        f"{row['within_2um_fraction_mean']:.0%}"
                    )
                twin, pi = s.get("mpc_twin"), s.get("pi")
                travel = (twin or {}).get("input_travel_mean") or {}
                overspray = "{} / {}".format(
                    _cell(twin, "mean_overspray_um", ".2f"), _cell(pi, "mean_overspray_um", ".2f")
                )
                solve = "{} / {}, {} / {}".format(
                    _cell(twin, "solve_ms_mean", ".1f"),
                    _cell(twin, "solve_ms_max", ".1f"),
                    _cell(twin, "solve_wall_ms_mean", ".1f"),
                    _cell(twin, "solve_wall_ms_max", ".1f"),
                )
                inside = twin is not None and twin["all_inside_limits"]
                limits = (
                    "–"
                    if twin is None
                    else ("inside" if inside and twin["all_rate_limits_respected"] else "VIOLATED")
                )
                generator = "first" if truth == "model" else "second"
                cells += [
                    _ratio(s, "open_loop"),
                    _ratio(s, "pi"),
                    overspray,
                    ", ".join(f"{v:.0f}" for v in travel.values()) or "–",
                    _cell(twin, "holds_mean", ".1f"),
                    limits,
                    solve,
                ]
                seeds = ",".join(block["per_seed"])
                lines.append(
                    f"| {scenario} | {camera} | {generator} | {seeds} | " + " | ".join(cells) + " |"
                )
    return "\n".join(lines) + "\n"


def _ratio(summary: dict, other: str) -> str:
    value = summary.get(f"ratio_rms_{other}_over_mpc_twin")
    return "–" if value is None else f"{value:.2f}×"


def parse_seed_list(text: str) -> list[int]:
    """Seeds from ``1-5``, ``0,6`` or a mix."""
    seeds: list[int] = []
    for part in (p.strip() for p in str(text).split(",") if p.strip()):
        first, _, last = part.partition("-")
        seeds += list(range(int(first), int(last or first) + 1))
    if not seeds or min(seeds) < 0:
        raise ValueError(f"seeds {text!r}: non-negative integers, e.g. 1-5 or 0,6")
    return seeds


def next_utc_time(text: str, now: datetime | None = None) -> float:
    """``HH:MM`` UTC as a :func:`time.time`: the next such moment, today or, when it has
    passed, tomorrow (a run started at 22:00 with ``--stop-at 01:00`` stops after midnight).

    >>> now = datetime(2026, 1, 1, 22, 0, tzinfo=UTC)
    >>> datetime.fromtimestamp(next_utc_time("01:30", now), UTC).isoformat()
    '2026-01-02T01:30:00+00:00'
    """
    hours, minutes = (int(v) for v in text.split(":"))
    now = datetime.now(UTC) if now is None else now
    moment = now.replace(hour=hours, minute=minutes, second=0, microsecond=0)
    return (moment if moment > now else moment + timedelta(days=1)).timestamp()


def main(argv=None) -> None:
    """``python -m ajtwin.studies.control {tune-pi,compare} …`` (docs/validation.md#control)."""
    parser = argparse.ArgumentParser(prog="python -m ajtwin.studies.control", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("tune-pi", "compare"):
        p = sub.add_parser(name)
        p.add_argument("--job", required=True, help="the program (.prg)")
        p.add_argument("--process-speed", default="2,4,3", help="speeds per layer (2,4,3)")
        p.add_argument("--repeat-pitch-mm", default="35,10", help="parts side by side")
        p.add_argument("--target", type=float, default=55.0, help="target L_w [µm]")
        p.add_argument("--out", required=True, help="JSON file (tune-pi) or folder (compare)")
    tune = sub.choices["tune-pi"]
    tune.add_argument("--offsets", default="0,5,20", help="camera offsets [mm] (0: nozzle)")
    tune.add_argument("--seeds", default="0,6")
    tune.add_argument("--minutes", type=float, default=45.0)
    comp = sub.choices["compare"]
    comp.add_argument("--offsets", default="0,5,20,inspection")
    comp.add_argument("--seeds", default="1-5")
    comp.add_argument("--minutes", type=float, default=90.0)
    comp.add_argument("--truth", default="model,alt")
    comp.add_argument("--scenarios", default=",".join(JOB_SCENARIOS))
    comp.add_argument("--core-scenarios", help="scenarios whose cells run every seed first")
    comp.add_argument("--core-offsets", help="camera offsets whose cells run every seed first")
    comp.add_argument("--stop-at", help="UTC HH:MM: no print starts that would end later")
    comp.add_argument("--records", help="folder of the records (default: --out)")
    comp.add_argument("--resume", action="store_true", help="keep the prints of --out's table")
    args = parser.parse_args(argv)
    text = args.process_speed
    speed = SpeedSchedule.parse(text) if ("," in text or ":" in text) else float(text)
    pitch = tuple(float(v) for v in args.repeat_pitch_mm.split(","))
    cameras = cameras_from_offsets(args.offsets, args.job, speed, pitch)
    seeds = parse_seed_list(args.seeds)
    t0 = time.time()
    if args.command == "tune-pi":
        result = tune_pi(cameras, seeds=seeds, minutes=args.minutes, target_um=args.target)
        result["command"] = "python -m ajtwin.studies.control " + " ".join(argv or sys.argv[1:])
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2))
    else:
        grid = ComparisonGrid(
            [s for s in args.scenarios.split(",") if s],
            seeds,
            args.target,
            duration_min=args.minutes,
        )
        result = job_comparison(
            cameras,
            grid,
            args.out,
            truths=tuple(args.truth.split(",")),
            core_scenarios=None if args.core_scenarios is None else args.core_scenarios.split(","),
            core_cameras=(
                None
                if args.core_offsets is None
                else list(cameras_from_offsets(args.core_offsets, args.job, speed, pitch))
            ),
            stop_at=None if args.stop_at is None else next_utc_time(args.stop_at),
            records_dir=args.records,
            resume=args.resume,
        )
        result["command"] = "python -m ajtwin.studies.control " + " ".join(argv or sys.argv[1:])
        (Path(args.out) / "metrics.json").write_text(json.dumps(result, indent=2))
    print(f"done in {time.time() - t0:.0f} s; wrote {args.out}")


if __name__ == "__main__":
    main()
