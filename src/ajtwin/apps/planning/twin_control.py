"""The MPC on the twin: a strategy that plans from the machine's twin as it runs.

:class:`MPCTwin` gives every sample of a period to a *monitored twin* — the machine's twin
core fed a sample at a time with the anomaly detectors on its committed steps (the live
engine's :class:`ajtwin.engine.stream.TwinStream`, whichever process owns it) — and starts
the MPC from its state now (a job print's provisional state of the newest row), its
covariance and θ, under the safety rules of :mod:`ajtwin.apps.planning.mpc`. The same class
steers the virtual printer in closed loop (``ajtwin control simulate``) and a real machine
over OPC UA (``ajtwin control --opcua``).

What it needs of the monitored twin is :class:`MonitoredTwin`: nothing here builds one.
"""

from __future__ import annotations

import functools
from typing import Protocol

import numpy as np

from ajtwin.apps.detection.causes import CAUSES
from ajtwin.apps.planning.mpc import (
    ink_supply_status,
    mismatch_reasons,
    vial_level_from_material_flow,
)
from ajtwin.apps.planning.strategies import Decision, MPCStrategy, linewidth_variance
from ajtwin.estimation.samples import Sample


class MonitoredTwin(Protocol):
    """What :class:`MPCTwin` reads of a machine's twin (the engine's ``TwinStream`` is one).

    ``core``: the twin's :class:`~ajtwin.estimation.online.OnlineTwin` (its committed state
    and recent NIS); ``provisional``: a job print's (time, mean, covariance) now;
    ``theta``: θ in force; ``detector``: the anomaly detectors (``vial_status``);
    ``status()``: ("alarm", cause) while an alarm stands.
    """

    core: object
    detector: object

    @property
    def provisional(self):
        """A job print's (time [s], mean (5,), covariance (5, 5)) now (None: none)."""

    @property
    def theta(self) -> np.ndarray:
        """θ in force [1/s]."""

    def feed(self, sample: Sample, provisional: bool = True) -> list:
        """Take one sample (with a job print's provisional re-run unless ``provisional``
        is False)."""

    def refresh_provisional(self) -> list:
        """A job print's provisional state of the newest row, re-run now."""

    def status(self, provisional: bool = False) -> tuple[str, str]:
        """("alarm", cause) while an alarm stands, else ("ok", "") or ("warming up", "")."""


class MPCTwin(MPCStrategy):
    """MPC on the twin: the monitored twin fed every sample, safety rules applied.

    Besides the safety rules of :mod:`ajtwin.apps.planning.mpc` it watches the ink supply
    (:func:`ajtwin.apps.planning.mpc.ink_supply_status`: its own ink balance from the measured
    Q_m and the twin's vial observer). A vial running dry is not controllable with these
    inputs, so on ``stop`` it latches: the inputs in force are held for the rest of the
    print (reason ``ink_low: …``) — a refill is maintenance and a new print. Of the
    detectors' alarms only those that make acting unsafe hold it (``hold_causes``: a fault
    of the inputs, a model that does not fit the machine, a deposit beyond the model's
    range; ``hold_detectors``: an alarm the filter's own consistency test raised, a sensor
    or the model off the data); through the others (a clog, atomizer trouble, an unexplained
    deviation that drift detectors raised: changes the twin follows in its states) it keeps
    acting and its reason names the alarm.

    Parameters
    ----------
    *args, **kwargs
        As :class:`~ajtwin.apps.planning.strategies.MPCStrategy` (twin, settings, bounds,
        u0, target, limits, max_overspray_um, job).
    stream : MonitoredTwin
        The machine's monitored twin.
    feed : callable(Sample), optional
        How a sample reaches it (a live engine's feed, which stores and publishes each
        step); default ``stream.feed`` without the provisional re-run, which this
        controller then does once per period, when it plans.
    """

    name = "mpc_twin"

    def __init__(self, *args, stream: MonitoredTwin, feed=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.stream = stream
        self._own_stream = feed is None
        self._feed = feed or functools.partial(self.stream.feed, provisional=False)
        self.holding = False
        # the ink balance starts from the fill the twin was told (weighed at the refill)
        self.vial_fill_ml = float(self.twin.config.vial_fill_ml)
        calibration = getattr(self.twin, "calibration", None)
        self.material_flow_gain = (
            float(calibration.material_flow_gain) if calibration is not None else 1.0
        )
        self.material_flow: list[np.ndarray] = []
        self.ink = None  # the latest InkSupply
        self.ink_stop: str | None = None  # the latched reason, once stopped

    def observe(self, chunk):
        """Feed every sample of the period to the twin (with a job print's shutter, platen
        speed and the camera's print times when the chunk has them)."""
        job = getattr(chunk, "printed_at_s", None) is not None
        for k, (t, u, y) in enumerate(zip(chunk.time_s, chunk.inputs, chunk.outputs)):
            extra = {}
            if job:
                extra = dict(
                    shutter_open=float(chunk.shutter_open[k]),
                    platen_speed_mm_s=float(chunk.platen_speed_mm_s[k]),
                    printed_at_s=float(chunk.printed_at_s[k]),
                )
            self._feed(Sample(float(t), u, y, **extra))
        if self._own_stream:
            self.stream.refresh_provisional()
        self.material_flow.append(np.asarray(chunk.outputs, dtype=float)[:, 4])

    def state_now(self):
        """(mean, cov) the MPC plans from: the committed step's, or on a job print the
        provisional state of the newest row (the steps after the last final one re-run with
        what the camera has filed so far); None before the twin has a state."""
        core = self.stream.core
        provisional = self.stream.provisional
        if provisional is not None and (
            core.n_committed == 0 or provisional[0] > core.last_time_committed
        ):
            return provisional[1], provisional[2]
        if core.n_committed == 0:
            return None
        return core.last_mean, core.last_cov

    def ink_supply(self):
        """The ink supply now (:func:`ajtwin.apps.planning.mpc.ink_supply_status`)."""
        q = np.concatenate(self.material_flow) if self.material_flow else np.array([])
        balance = vial_level_from_material_flow(
            q, self.vial_fill_ml, self.material_flow_gain, self.twin.model.params
        )
        observer = getattr(getattr(self.stream, "detector", None), "vial_status", None)
        self.ink = ink_supply_status(balance, observer, self.settings)
        return self.ink

    def safety(self, mean=None):
        """Reasons not to act now (empty: act). ``mean``: the state the MPC plans from
        (default the committed one); before the first final step of a job print only its
        physical range can be checked (the detectors see steps H s after they are printed)."""
        core = self.stream.core
        if core.n_committed == 0:
            if mean is None:
                return ["the twin has not started (initial fit pending)"]
            return self.state_limits.violations(np.asarray(mean))
        mean = core.last_mean if mean is None else np.asarray(mean)
        window = self.settings.nis_window_s
        reasons = mismatch_reasons(
            mean,
            core.recent("nis", window),
            core.recent("n_measured", window),
            limits=self.state_limits,
            settings=self.settings,
            status=getattr(self.stream, "mismatch_status", None),
        )
        # only an alarm that makes acting unsafe holds (data/control.toml hold_causes,
        # hold_detectors); the others are changes of the machine the twin follows ('ink
        # running out' is the ink rule's: it steers while the vial is inside H's fit and
        # stops for good before)
        cause, detectors = self.standing_alarm()
        name = CAUSES.get(cause, cause)
        if cause in self.settings.hold_causes:
            reasons.append(f"alarm that makes acting unsafe: {name}")
        elif cause is not None and cause != "ink_low":
            inconsistent = [d for d in detectors if d in self.settings.hold_detectors]
            if inconsistent:
                reasons.append(
                    f"alarm that makes acting unsafe: {name}, raised by the filter's own "
                    f"consistency test ({', '.join(inconsistent)}): a sensor or the model "
                    "does not fit"
                )
        return reasons

    def standing_alarm(self) -> tuple[str | None, list]:
        """(cause, detectors) of the alarm standing now ((None, []): none)."""
        status, cause = self.stream.status()
        if status != "alarm":
            return None, []
        events = getattr(getattr(self.stream, "detector", None), "events", None) or []
        return cause, list(events[-1].detectors) if events else []

    def decide(self, t, u):
        """Stop for the ink, hold for a safety reason, else the MPC's command from the twin's
        state."""
        if self.ink_stop:
            # latched: nothing the controller does brings the ink back
            return Decision(u.copy(), "stop", self.ink_stop)
        state = self.state_now()
        if state is None:
            return Decision(u.copy(), "warm-up", "waiting for the twin's initial fit")
        mean, cov = state
        ink = self.ink_supply()
        if ink.status == "stop":
            self.ink_stop = f"{ink.reason}; inputs held for the rest of the print (refill)"
            self.mpc.reset()
            return Decision(u.copy(), "stop", self.ink_stop)
        reasons = self.safety(mean)
        if reasons:
            self.mpc.reset()
            return Decision(u.copy(), "hold", "; ".join(reasons))
        sigma = float(
            np.sqrt(max(linewidth_variance(self.twin.model.coefficient_matrix[0], mean, cov), 0.0))
        )
        decision = self._act(mean, cov, self.stream.theta, u, sigma, t=t)
        notes = [decision.reason, ink.reason if ink.status == "low" else ""]
        cause, _ = self.standing_alarm()
        if cause is not None and cause != "ink_low":
            notes.append(
                f"acting through the alarm {CAUSES.get(cause, cause)}: not a fault of the "
                "inputs, the twin follows it in its states"
            )
        decision.reason = "; ".join(r for r in notes if r)
        return decision
