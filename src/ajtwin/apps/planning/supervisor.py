"""The rules around a controller on a real machine: when to decide, what may be written.

A controller (the MPC on the twin, :class:`~ajtwin.apps.planning.twin_control.MPCTwin`)
says what it would set; :class:`Supervisor` decides what reaches the machine, the same way
whatever the link:

* a decision every ``period_s`` of print time, never two within a period of the
  machine's own clock (a controller that lags behind its samples must not bunch moves);
* no move during the warm-up (the first ``warmup_s`` of print);
* every command through :func:`~ajtwin.apps.planning.mpc.clip_command`: inside the limits
  (the registry's ∩ what the machine accepts ∩ the fit's validity) and within the rate
  limits × the period;
* a value outside the machine's limits (on the way back from an operator's out-of-range
  setting) is not written, and the reason says so;
* the target is checked against the reachable range once the twin has a state
  (:class:`~ajtwin.apps.planning.mpc.TargetError` when out of reach).

Examples
--------
>>> target = ControlTarget(65.0)
>>> target.resolved().limits["carrier_flow_sccm"]
[15.0, 35.0]
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.mpc import (
    ControlSettings,
    check_target,
    clip_command,
    reachable_linewidth,
)
from ajtwin.apps.planning.strategies import Decision
from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.model.names import INPUT_NAMES


@dataclass(frozen=True)
class ControlTarget:
    """What a controlled print aims at, and within what.

    Attributes
    ----------
    target_um : float
        Target linewidth [µm].
    max_overspray_um : float, optional
        Soft limit on L_o [µm].
    limits : dict, optional
        The machine's input limits {input column: [low, high]} (default: the packaged ones).
    settings : ControlSettings, optional
        The controller's settings (default ``data/control.toml``).
    vial_fill_ml : float, optional
        The vial's fill as weighed at the refill [mL] (default: the twin's).
    """

    target_um: float
    max_overspray_um: float | None = None
    limits: dict | None = None
    settings: ControlSettings | None = None
    vial_fill_ml: float | None = None

    def resolved(self) -> ControlTarget:
        """The target checked, with the default limits and settings filled in."""
        target = check_target(self.target_um)
        fill = self.vial_fill_ml
        if fill is not None and not (np.isfinite(fill) and fill > 0):
            raise ValueError(f"vial fill = {fill!r} mL must be a positive number")
        limits = {k: list(v) for k, v in (self.limits or DEFAULT_LIMITS).items()}
        return replace(
            self,
            target_um=target,
            limits=limits,
            settings=self.settings or ControlSettings.load(),
        )


@dataclass
class ControlDecision:
    """One control period: what was decided and what was written."""

    time_s: float
    status: str  # act | hold | warm-up | stop
    reason: str
    command: list  # [mA, sccm, sccm] in force after the period's write
    written: dict = field(default_factory=dict)  # {column: value} to write (empty: none)
    solve_ms: float = float("nan")
    predicted_linewidth_um: float = float("nan")


class Supervisor:
    """The rules between a controller and the machine (module docstring).

    Parameters
    ----------
    controller : object
        ``decide(t, u) -> Decision`` and ``state_now() -> (mean, cov) | None``; its
        ``twin`` (for the reachable range) and ``mpc`` (rebuilt when the limits narrow).
    target : ControlTarget
        Resolved (:meth:`ControlTarget.resolved`).
    """

    def __init__(self, controller, target: ControlTarget):
        self.controller = controller
        self.target = target
        self.settings = target.settings
        self.limits = {k: list(v) for k, v in target.limits.items()}
        self.bounds = effective_bounds(self.limits)
        self.next_decision_s: float | None = None
        self.last_write_s: float | None = None  # the machine's clock at the last write
        self.reachable: tuple[float, float] | None = None

    def narrow_limits(self, ranges: dict) -> bool:
        """Intersect the limits with what the machine accepts ({column: (low, high)});
        True when they narrowed (the MPC is rebuilt on them). A range that does not meet
        the limits is a ValueError naming both."""
        changed = False
        for column, (low, high) in ranges.items():
            lo, hi = self.limits[column]
            new = [max(lo, low), min(hi, high)]
            if not new[0] < new[1]:
                raise ValueError(
                    f"{column}: the machine's range [{low}, {high}] and the limits "
                    f"[{lo}, {hi}] do not overlap"
                )
            if new != [lo, hi]:
                changed = True
                self.limits[column] = new
        if changed:
            self.bounds = effective_bounds(self.limits)
            c = self.controller
            c.mpc = type(c.mpc)(c.twin, self.settings, self.limits, self.target.max_overspray_um)
            c.mpc.warm_up()
        return changed

    def saw(self, first_time_s: float) -> None:
        """Samples from ``first_time_s`` on have reached the controller (the first decision
        comes a period after the first)."""
        if self.next_decision_s is None:
            self.next_decision_s = first_time_s + self.settings.period_s

    def due(self, last_time_s: float) -> bool:
        """Whether a decision is due now that the samples reach ``last_time_s``."""
        return self.next_decision_s is not None and last_time_s >= self.next_decision_s

    def check_reachable(self) -> tuple[float, float] | None:
        """Once the twin has a state: the reachable range, the target checked against it
        (:class:`~ajtwin.apps.planning.mpc.TargetError` when out of reach)."""
        if self.reachable is not None:
            return self.reachable
        state = self.controller.state_now()
        if state is None:
            return None
        reach = reachable_linewidth(self.controller.twin, state[0], state[1], self.bounds)
        check_target(self.target.target_um, reach)
        self.reachable = reach
        return reach

    def decide(self, t: float, u, machine_now_s: float) -> ControlDecision | None:
        """The decision for the period ending at print time ``t`` [s], from the command in
        force ``u`` (3,) read from the machine, at the machine's clock ``machine_now_s``;
        None when a period of the machine's clock has not passed since the last write
        (asked again at the next sample)."""
        s = self.settings
        if self.last_write_s is not None and machine_now_s - self.last_write_s < s.period_s:
            self.next_decision_s = t
            return None
        self.next_decision_s = t - 1 + s.period_s
        u = np.asarray(u, dtype=float)
        if t < s.warmup_s:
            decision = Decision(u.copy(), "warm-up", f"first {s.warmup_s} s of print")
        else:
            decision = self.controller.decide(t, u)
        max_step = np.asarray(s.rate_limits) * s.period_s  # ≥ one period since the last write
        command = clip_command(decision.command, u, self.bounds, max_step)
        changes, reason = {}, decision.reason
        for column, v, old in zip(INPUT_NAMES, command, u):
            low, high = self.limits[column]
            if abs(float(v) - float(old)) <= 1e-9:
                continue
            if not low <= v <= high:
                reason += f"; {column} {v:g} not written (outside [{low:g}, {high:g}])"
                continue
            changes[column] = float(v)
        if decision.status != "act":
            changes = {}
        return ControlDecision(
            t,
            decision.status,
            reason.lstrip("; "),
            [changes.get(column, float(old)) for column, old in zip(INPUT_NAMES, u)],
            changes,
            decision.solve_s * 1e3,
            decision.predicted_linewidth_um,
        )

    def written(self, machine_now_s: float) -> None:
        """The decision's changes were written at the machine's clock ``machine_now_s``."""
        self.last_write_s = float(machine_now_s)
