"""The closed loop: a controller drives the virtual printer from its measurements.

The virtual printer (:class:`ajtwin.simulation.stepper.SteppedPrinter`) prints a period of
``period_s`` seconds under the command in force; the controller (a strategy of
:mod:`ajtwin.apps.planning.strategies`, or the MPC on the twin,
:class:`ajtwin.apps.planning.twin_control.MPCTwin`) sees the reported inputs and the measured
outputs of that period and issues the next command. Every command passes
:func:`ajtwin.apps.planning.mpc.clip_command` (limits and rate limits), and the whole run
is checked against them afterwards (:func:`run_closed_loop`).

Metrics (on the *true*, noise-free line printed at the nozzle, after the warm-up), per
printed length: each second weighs the length it printed, ν(t_k) at its speed, 0 with the
shutter closed (a straight line without a job: every second alike): RMS error of L_w to the
target, the fraction of the printed length within ±2 µm, mean and max overspray, input
travel Σ|Δ set-point| per input, CPU time per MPC solve, holds and their reasons
(:func:`closed_loop_metrics`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.apps.planning.mpc import ControlSettings, clip_command
from ajtwin.apps.planning.strategies import Decision
from ajtwin.model.line_speed import load_line_speed_law
from ajtwin.model.names import INPUT_NAMES

STRATEGIES = ("open_loop", "pi", "mpc_nominal", "mpc_twin")
CONTROL_SCENARIO_DIR = resources.files("ajtwin") / "data" / "control_scenarios"


def resolve_scenario(name):
    """A packaged scenario name, one of the controller's own (``slow_clog``) or a path."""
    text = str(name)
    own = CONTROL_SCENARIO_DIR / f"{text}.toml"
    if not text.endswith(".toml") and own.is_file():
        return Path(str(own))
    return name


@dataclass
class ClosedLoopRun:
    """One closed-loop print.

    Attributes
    ----------
    strategy, scenario : str
    seed : int
    target_um : float
        Target linewidth [µm].
    record : PrintRecord
        What the printer logged.
    commands : DataFrame
        One row per control period: the command, status, reason, solve time.
    true_outputs : array (T, 5)
        The printer's noise-free outputs (the line at ν_ref, the shutter ignored).
    setpoints : array (T, 3)
        The set-points in force each second [mA, sccm, sccm].
    metrics : dict
        :func:`closed_loop_metrics`.
    true_line : array (T, 2)
        The true L_w, L_o printed at the nozzle each second (NaN: nothing printed).
    printed_length : array (T,)
        Each second's weight in the metrics: the length printed relative to a second at
        ν_ref (ones without a job).
    """

    strategy: str
    scenario: str
    seed: int
    target_um: float
    record: object  # PrintRecord
    commands: pd.DataFrame  # one row per control period
    true_outputs: np.ndarray  # (T, 5)
    setpoints: np.ndarray  # (T, 3)
    metrics: dict = field(default_factory=dict)
    true_line: np.ndarray | None = None  # (T, 2) the line at the nozzle
    printed_length: np.ndarray | None = None  # (T,) per-second weight


def printed_line(record, true_outputs) -> tuple[np.ndarray, np.ndarray]:
    """The true line printed each second (T, 2) and its printed length relative to a second
    at ν_ref (T,): a job print's ``true_linewidth_um``/``true_overspray_um`` and ν(t_k) · shutter
    / ν_ref; a straight line's true outputs, every second weighing 1."""
    if not getattr(record, "has_job", False):
        return np.asarray(true_outputs, dtype=float)[:, :2], np.ones(len(true_outputs))
    data = record.data
    line = data[["true_linewidth_um", "true_overspray_um"]].to_numpy(dtype=float)
    nu_ref = load_line_speed_law().reference_speed_mm_s
    length = np.asarray(record.shutter_open, dtype=float) * np.asarray(record.platen_speed)
    length = np.where(np.isfinite(line[:, 0]), np.nan_to_num(length), 0.0) / nu_ref
    return line, length


def run_closed_loop(
    printer,
    controller,
    *,
    strategy: str,
    target_um: float,
    u0,
    settings: ControlSettings,
    bounds,
    seed: int,
    truth: str,
    vial_fill_ml: float,
    progress=None,
) -> ClosedLoopRun:
    """Let ``controller`` drive ``printer`` (a SteppedPrinter) to the end of its print.

    Parameters
    ----------
    printer : SteppedPrinter
        The virtual printer, at its start.
    controller : object
        ``observe(chunk)`` and ``decide(t, u) -> Decision`` (a strategy).
    strategy : str
        The strategy's name, kept in the record's metadata.
    target_um : float
        Target linewidth [µm].
    u0 : array (3,)
        Start inputs [mA, sccm, sccm].
    settings : ControlSettings
        Period, warm-up and rate limits.
    bounds : array (3, 2)
        Input limits [mA, sccm, sccm].
    seed : int
        The print's seed (kept with the run).
    truth : str
        The printer's truth generator (kept in the metadata).
    vial_fill_ml : float
        The vial fill the twin was told [mL] (kept in the metadata).
    progress : callable(int), optional
        Seconds printed per period.
    """
    max_step = np.asarray(settings.rate_limits) * settings.period_s
    u = np.asarray(u0, dtype=float).copy()
    printer.set_setpoints(u)
    rows = []
    while not printer.done:
        chunk = printer.advance(settings.period_s)
        controller.observe(chunk)
        t = float(chunk.time_s[-1] + 1)
        if printer.done:
            break
        if t < settings.warmup_s:
            decision = Decision(u.copy(), "warm-up", f"first {settings.warmup_s} s")
        else:
            decision = controller.decide(t, u)
        command = clip_command(decision.command, u, bounds, max_step)
        rows.append(_command_row(t, command, decision))
        u = command
        printer.set_setpoints(u)
        if progress:
            progress(len(chunk.time_s))
    meta = {
        "control": {
            "strategy": strategy,
            "target_linewidth_um": target_um,
            "start_inputs": np.asarray(u0, dtype=float).tolist(),
            "settings": settings.source,
            "period_s": settings.period_s,
            "truth_generator": truth,
            "vial_fill_told_ml": float(vial_fill_ml),
        }
    }
    record = printer.record(extra_meta=meta)
    true_line, length = printed_line(record, printer.true_outputs)
    run = ClosedLoopRun(
        strategy,
        printer.scenario.name,
        int(seed),
        target_um,
        record,
        pd.DataFrame(rows),
        printer.true_outputs.copy(),
        printer.processes.setpoints[: printer.k].copy(),
        true_line=true_line,
        printed_length=length,
    )
    run.metrics = closed_loop_metrics(run, settings, bounds)
    return run


def _command_row(t: float, command, decision: Decision) -> dict:
    """One row of a run's command table: the command in force from ``t`` and why."""
    return {
        "time_s": t,
        **{name: float(v) for name, v in zip(INPUT_NAMES, command)},
        "status": decision.status,
        "reason": decision.reason,
        "solve_ms": decision.solve_s * 1e3,
        "solve_wall_ms": decision.solve_wall_s * 1e3,
        "predicted_linewidth_um": decision.predicted_linewidth_um,
        "predicted_linewidth_std_um": decision.predicted_linewidth_std_um,
        "step_scale": decision.step_scale,
    }


def closed_loop_metrics(run: ClosedLoopRun, settings: ControlSettings, bounds) -> dict:
    """The comparison's figures of one run (the true line, after the warm-up, per printed
    length: module docstring)."""
    k0 = int(settings.warmup_s)
    line, length = run.true_line, run.printed_length
    if line is None:
        line, length = run.true_outputs[:, :2], np.ones(len(run.true_outputs))
    weight = np.asarray(length, dtype=float)[k0:]
    lw, lo_ = line[k0:, 0], line[k0:, 1]
    printed = (weight > 0) & np.isfinite(lw)
    weight = np.where(printed, weight, 0.0)
    weight = weight / max(weight.sum(), 1e-300)
    err = np.where(printed, lw - run.target_um, 0.0)
    lo_ = np.where(printed, lo_, 0.0)
    sp = run.setpoints
    travel = np.abs(np.diff(sp, axis=0)).sum(axis=0)
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    steps = np.abs(np.diff(sp, axis=0))
    max_step = np.asarray(settings.rate_limits) * settings.period_s
    inside = bool(np.all(sp >= lo - 1e-9) and np.all(sp <= hi + 1e-9))
    rate_ok = bool(np.all(steps <= max_step * (1 + 1e-9) + 1e-12))
    c = run.commands
    solve = c["solve_ms"].to_numpy(float) if len(c) else np.array([])
    solve = solve[np.isfinite(solve)]
    wall = c["solve_wall_ms"].to_numpy(float) if "solve_wall_ms" in c else np.array([])
    wall = wall[np.isfinite(wall)]
    holds = c[c["status"] == "hold"] if len(c) else c
    reasons = {}
    if len(holds) and run.strategy != "open_loop":
        for t, reason in zip(holds["time_s"], holds["reason"]):
            reasons.setdefault(reason, float(t))
    stops = c[c["status"] == "stop"] if len(c) else c
    reasons_text = c["reason"].fillna("").astype(str) if len(c) else pd.Series([], dtype=str)
    low = c[reasons_text.str.contains("ink running low")] if len(c) else c
    return {
        "rms_error_um": float(np.sqrt(np.sum(weight * err**2))),
        "mean_error_um": float(np.sum(weight * err)),
        "within_2um_fraction": float(np.sum(weight * (np.abs(err) <= 2.0))),
        "mean_overspray_um": float(np.sum(weight * lo_)),
        "max_overspray_um": float(np.max(lo_[printed])) if printed.any() else None,
        "printed_length_mm": float(
            np.sum(np.asarray(length, dtype=float)[k0:][printed])
            * load_line_speed_law().reference_speed_mm_s
        ),
        "input_travel": {n: float(v) for n, v in zip(INPUT_NAMES, travel)},
        "solve_ms_mean": float(np.mean(solve)) if solve.size else None,
        "solve_ms_p95": float(np.percentile(solve, 95)) if solve.size else None,
        "solve_ms_max": float(np.max(solve)) if solve.size else None,
        "solve_wall_ms_mean": float(np.mean(wall)) if wall.size else None,
        "solve_wall_ms_p95": float(np.percentile(wall, 95)) if wall.size else None,
        "solve_wall_ms_max": float(np.max(wall)) if wall.size else None,
        "n_commands": int(len(c)),
        "n_holds": int(len(holds)) if run.strategy != "open_loop" else 0,
        "first_hold_s": (
            float(holds["time_s"].iloc[0]) if len(holds) and run.strategy != "open_loop" else None
        ),
        "hold_reasons": {r: t for r, t in list(reasons.items())[:5]},
        # the ink supply (mpc_twin): a latched stop, and the earlier 'running low' warning
        "ink_stop_s": float(stops["time_s"].iloc[0]) if len(stops) else None,
        "ink_stop_reason": str(stops["reason"].iloc[0]) if len(stops) else None,
        "n_stopped": int(len(stops)),
        "ink_low_warning_s": float(low["time_s"].iloc[0]) if len(low) else None,
        "inside_limits": inside,
        "rate_limits_respected": rate_ok,
        "final_setpoints": sp[-1].tolist(),
    }


# --------------------------------------------------------------------------- #
# The comparison: strategies × scenarios × seeds
# --------------------------------------------------------------------------- #


# --------------------------------------------------------------------------- #
# Merging runs made apart (per seed, per scenario, per truth generator)
# --------------------------------------------------------------------------- #
