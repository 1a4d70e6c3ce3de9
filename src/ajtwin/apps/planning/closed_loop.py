"""The closed loop: a controller drives the virtual printer from its measurements.

The virtual printer (:class:`ajtwin.simulation.stepper.SteppedPrinter`) prints a period of
``period_s`` seconds under the command in force; the controller (a strategy of
:mod:`ajtwin.apps.planning.strategies`, or the MPC on the streaming twin,
:class:`ajtwin.engine.control.MPCTwin`) sees the reported inputs and the measured outputs
of that period and issues the next command. Every command passes
:func:`ajtwin.apps.planning.mpc.clip_command` (limits and rate limits), and the whole run
is checked against them afterwards (:func:`run_closed_loop`).

Metrics (on the *true*, noise-free L_w and L_o from the printer, after the warm-up):
RMS error of L_w to the target, fraction of time within ±2 µm, mean and max overspray,
input travel Σ|Δ set-point| per input, CPU time per MPC solve, holds and their reasons
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
        The printer's noise-free outputs.
    setpoints : array (T, 3)
        The set-points in force each second [mA, sccm, sccm].
    metrics : dict
        :func:`closed_loop_metrics`.
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
    run = ClosedLoopRun(
        strategy,
        printer.scenario.name,
        int(seed),
        target_um,
        printer.record(extra_meta=meta),
        pd.DataFrame(rows),
        printer.true_outputs.copy(),
        printer.processes.setpoints[: printer.k].copy(),
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
        "predicted_linewidth_um": decision.predicted_linewidth_um,
        "predicted_linewidth_std_um": decision.predicted_linewidth_std_um,
        "step_scale": decision.step_scale,
    }


def closed_loop_metrics(run: ClosedLoopRun, settings: ControlSettings, bounds) -> dict:
    """The comparison's figures of one run (true outputs, after the warm-up)."""
    k0 = int(settings.warmup_s)
    lw = run.true_outputs[k0:, 0]
    lo_ = run.true_outputs[k0:, 1]
    err = lw - run.target_um
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
    holds = c[c["status"] == "hold"] if len(c) else c
    reasons = {}
    if len(holds) and run.strategy != "open_loop":
        for t, reason in zip(holds["time_s"], holds["reason"]):
            reasons.setdefault(reason, float(t))
    stops = c[c["status"] == "stop"] if len(c) else c
    reasons_text = c["reason"].fillna("").astype(str) if len(c) else pd.Series([], dtype=str)
    low = c[reasons_text.str.contains("ink running low")] if len(c) else c
    return {
        "rms_error_um": float(np.sqrt(np.mean(err**2))),
        "mean_error_um": float(np.mean(err)),
        "within_2um_fraction": float(np.mean(np.abs(err) <= 2.0)),
        "mean_overspray_um": float(np.mean(lo_)),
        "max_overspray_um": float(np.max(lo_)),
        "input_travel": {n: float(v) for n, v in zip(INPUT_NAMES, travel)},
        "solve_ms_mean": float(np.mean(solve)) if solve.size else None,
        "solve_ms_p95": float(np.percentile(solve, 95)) if solve.size else None,
        "solve_ms_max": float(np.max(solve)) if solve.size else None,
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
