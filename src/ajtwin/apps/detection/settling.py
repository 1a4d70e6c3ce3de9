"""Ready to print: when the twin's states and the printed line have settled after start-up.

At switch-on the atomizer's mist builds up and its droplets settle over minutes (5–15 min
is the run-in commonly reported for AJ systems); a line printed before then drifts. Per
second the twin gives its states (mean, σ) and its predicted outputs; the detector watches
four signals — the predicted L_w and L_o, d_a and φ_A (relative) — and over a trailing
window of ``window_s`` seconds fits each one's linear trend b (least squares). The change
still to come is judged as |b|·``horizon_s``: for an exponential settling with time constant
τ ≤ horizon, the rest of the way is b·τ ≤ |b|·horizon. *Ready* when every signal's projected
change is within its tolerance (``data/settling.toml``) for ``hold_s`` seconds in a row; the
evidence is each signal's trend and projected change then.

:class:`SettlingDetector` takes a run a chunk (or a step) at a time — the live twin feeds it
each chunk it publishes — and :func:`settling_time` a whole run at once; the two give the
same answer (the online one keeps the last window of samples between chunks).

Examples
--------
>>> t = np.arange(900.0)
>>> level = 40.0 + 8.0 * (1 - np.exp(-t / 120.0))          # a line settling, τ = 2 min
>>> means = np.column_stack([np.full(900, 3.5), np.ones(900), np.zeros(900), np.zeros(900),
...                          4.6e-7 * (1 - 0.5 * np.exp(-t / 120.0))])
>>> outputs = np.column_stack([level, level / 5, np.zeros(900), np.zeros(900), np.zeros(900)])
>>> r = settling_time(t, means, outputs)
>>> r.ready, 500 < r.ready_at_s < 800
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.model.names import OUTPUT_NAMES, STATE_NAMES

#: The watched signals: (name, source, column, relative)
SIGNALS = (
    ("linewidth_um", "outputs", 0, False),
    ("overspray_um", "outputs", 1, False),
    ("droplet_diameter_um", "states", 0, False),
    ("aerosol_relative", "states", 4, True),
)


@dataclass(frozen=True)
class SettlingSettings:
    """The detector's window, horizon, hold [s] and per-signal tolerances."""

    window_s: int = 120
    horizon_s: float = 300.0
    hold_s: int = 30
    tolerances: tuple = (1.5, 1.5, 0.10, 0.06)
    atomizer_off_mA: float = 50.0

    @classmethod
    def load(cls) -> SettlingSettings:
        """``data/settling.toml``."""
        s = packaged_toml("data/settling.toml")["settling"]
        return cls(
            int(s["window_s"]),
            float(s["horizon_s"]),
            int(s["hold_s"]),
            tuple(float(s[name]) for name, *_ in SIGNALS),
            float(s.get("atomizer_off_mA", 50.0)),
        )


@dataclass
class Readiness:
    """The verdict: ready (and since when [s]), with the evidence per signal at that time
    (trend per minute and projected change over the horizon, in the signal's units)."""

    ready: bool
    ready_at_s: float | None = None
    evidence: dict = field(default_factory=dict)

    def sentence(self) -> str:
        """One line for a user (print time in minutes, each signal in words)."""
        if not self.ready:
            return "not settled yet: " + _evidence_text(self.evidence)
        since = f"ready to print from {self.ready_at_s / 60:.1f} min: "
        return since + _evidence_text(self.evidence)


#: how a watched signal is said: (words, unit)
SIGNAL_WORDS = {
    "linewidth_um": ("linewidth", "µm"),
    "overspray_um": ("overspray", "µm"),
    "droplet_diameter_um": ("droplet size", "µm"),
    "aerosol_relative": ("aerosol density", "relative"),
}


def _evidence_text(evidence: dict) -> str:
    if not evidence:
        return "too few samples yet (2 min are needed)"
    parts = []
    for name, e in evidence.items():
        words, unit = SIGNAL_WORDS.get(name, (name, ""))
        unit = f" {unit}" if unit and unit != "relative" else ""
        parts.append(
            f"{words} moving {e['trend_per_min']:+.2g}{unit}/min, {e['projected']:.2g}{unit} "
            f"still to come (allowed {e['tolerance']:g}{unit})"
        )
    return "; ".join(parts)


def rolling_trends(time_s, values, window: int) -> np.ndarray:
    """Least-squares slope of ``values`` (T, K) over each trailing window of ``window``
    samples (NaN before a full window or where a value is missing), per second (T, K)."""
    t = np.asarray(time_s, dtype=float)
    y = np.asarray(values, dtype=float)
    n = len(t)
    out = np.full(y.shape, np.nan)
    if n < window:
        return out
    t0 = t - t[0]  # keep the sums well conditioned

    def windowed(a):
        c = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])
        return c[window:] - c[:-window]

    st, stt = windowed(t0), windowed(t0 * t0)
    sy, sty = windowed(y), windowed(t0[:, None] * y)
    missing = windowed(np.isnan(y).astype(float))
    denominator = window * stt - st**2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (window * sty - st[:, None] * sy) / denominator[:, None]
    slope[missing > 0] = np.nan
    out[window - 1 :] = slope
    return out


class SettlingDetector:
    """The online detector (module docstring); feed it with :meth:`update`."""

    def __init__(self, settings: SettlingSettings | None = None):
        self.settings = settings or SettlingSettings.load()
        self._time = np.zeros(0)
        self._signals = np.zeros((0, len(SIGNALS)))
        self._reference_aerosol = None
        self._run = 0
        self.readiness = Readiness(False)

    def _signal_columns(self, means, outputs) -> np.ndarray:
        means = np.atleast_2d(np.asarray(means, dtype=float))
        outputs = np.atleast_2d(np.asarray(outputs, dtype=float))
        if self._reference_aerosol is None:
            finite = means[np.isfinite(means[:, 4]), 4]
            self._reference_aerosol = float(np.abs(finite[0])) if len(finite) else 1.0
        cols = []
        for _, source, column, relative in SIGNALS:
            values = (outputs if source == "outputs" else means)[:, column]
            cols.append(values / max(self._reference_aerosol, 1e-30) if relative else values)
        return np.column_stack(cols)

    def update(self, time_s, means, outputs) -> Readiness:
        """Take the next steps: times (n,) [s], state means (n, 5), the twin's predicted
        outputs (n, 5); returns the verdict so far (once ready, it stays ready)."""
        if self.readiness.ready:
            return self.readiness
        s = self.settings
        time_s = np.atleast_1d(np.asarray(time_s, dtype=float))
        signals = self._signal_columns(means, outputs)
        keep = s.window_s - 1
        t = np.concatenate([self._time[-keep:] if keep else self._time[:0], time_s])
        y = np.concatenate([self._signals[-keep:] if keep else self._signals[:0], signals])
        first_new = len(t) - len(time_s)
        trends = rolling_trends(t, y, s.window_s)
        projected = np.abs(trends) * s.horizon_s
        within = np.all(projected <= np.array(s.tolerances), axis=1)  # NaN → False
        for k in range(first_new, len(t)):
            self._run = self._run + 1 if within[k] else 0
            if self._run >= s.hold_s:
                self.readiness = Readiness(
                    True, float(t[k]), self._evidence(trends[k], projected[k])
                )
                break
        else:
            if len(t):
                self.readiness = Readiness(False, None, self._evidence(trends[-1], projected[-1]))
        self._time, self._signals = t, y
        return self.readiness

    def _evidence(self, trend, projected) -> dict:
        if not np.all(np.isfinite(trend)):
            return {}
        return {
            name: {
                "trend_per_min": float(trend[i] * 60.0),
                "projected": float(projected[i]),
                "tolerance": self.settings.tolerances[i],
            }
            for i, (name, *_) in enumerate(SIGNALS)
        }

    def status(self) -> dict:
        """JSON-ready: ready, since when, the evidence."""
        r = self.readiness
        return {
            "ready": r.ready,
            "ready_at_s": r.ready_at_s,
            "evidence": r.evidence,
            "text": r.sentence(),
        }


def atomizer_restarts(atomizer_current_mA, was_off: bool, off_mA: float) -> tuple[list[int], bool]:
    """Where the atomizer starts again in a run of samples: the indices of the samples
    at or above ``off_mA`` that follow one below it (``was_off``: the sample before the
    first was below), and whether the last is below. A missing current (NaN) changes
    nothing.

    >>> atomizer_restarts([375.0, 0.0, 0.0, 375.0, 380.0, np.nan, 0.0], False, 50.0)
    ([3], True)
    """
    restarts, off = [], bool(was_off)
    for k, current in enumerate(np.asarray(atomizer_current_mA, dtype=float)):
        if not np.isfinite(current):
            continue
        if current < off_mA:
            off = True
        elif off:
            restarts.append(k)
            off = False
    return restarts, off


def switched_on_s(meta) -> float | None:
    """When a record's atomizer was switched on (its metadata ``atomizer_switched_on_s``,
    seconds on the record's clock; the virtual printer's start-up sets it): the print
    begins with a run-in. None: not known (a print of a running atomizer, as far as the
    record says).

    >>> switched_on_s({"atomizer_switched_on_s": 0}), switched_on_s({})
    (0.0, None)
    """
    value = (meta or {}).get("atomizer_switched_on_s")
    return None if value is None else float(value)


class RunIn:
    """The atomizer's run-ins over a print, a step at a time: each begins at a switch-on
    (the record's, :func:`switched_on_s`, or a sample at or above ``atomizer_off_mA`` after
    one below it: :func:`atomizer_restarts`) and ends when the twin says ready to print (a
    new :class:`SettlingDetector` per run-in). A print whose atomizer was already running
    has none: every test that reads a run-in is then what it was without it.

    Examples
    --------
    >>> run_in = RunIn(switched_on_s=0.0)
    >>> for t in range(3):
    ...     run_in.update(float(t), 375.0, np.zeros(5), np.zeros(5))
    >>> run_in.spans, run_in.covers(2.0), RunIn().covers(2.0)
    ([[0.0, None]], True, False)
    """

    def __init__(self, switched_on_s: float | None = None, settings=None):
        self.settings = settings or SettlingSettings.load()
        self._switch_on = switched_on_s
        self._off = False
        self._detector: SettlingDetector | None = None
        self.spans: list[list] = []  # [start s, ready s or None (not yet)] per run-in

    def update(self, time_s: float, current_mA, mean, predicted_output) -> None:
        """One step: its time [s], the atomizer current [mA] (None or NaN: not known), the
        twin's state mean (5,) and predicted outputs (5,)."""
        t = float(time_s)
        if self._switch_on is not None and t >= self._switch_on:
            self._switch_on = None
            self._begin(t)
        if current_mA is not None:
            off_mA = self.settings.atomizer_off_mA
            restarts, self._off = atomizer_restarts([current_mA], self._off, off_mA)
            if restarts:
                self._begin(t)
        if self._detector is not None:
            verdict = self._detector.update(
                [t], np.asarray(mean, dtype=float)[None], np.asarray(predicted_output)[None]
            )
            if verdict.ready:
                self.spans[-1][1] = verdict.ready_at_s
                self._detector = None

    def _begin(self, t: float) -> None:
        self._detector = SettlingDetector(self.settings)
        self.spans.append([t, None])

    def covers(self, time_s: float) -> bool:
        """Whether ``time_s`` lies in a run-in (after a switch-on, before ready to print)."""
        return any(a <= time_s and (b is None or time_s < b) for a, b in self.spans)


class StartupWatch:
    """Ready to print over a live print: a :class:`SettlingDetector` fed a block of
    committed steps at a time, a new one whenever the atomizer starts again (its run-in
    begins again), and the verdict as of each step: never ready while the atomizer is off.

    Examples
    --------
    >>> watch = StartupWatch()
    >>> t = np.arange(3.0)
    >>> u = np.array([[375.0, 23.0, 50.0], [0.0, 23.0, 50.0], [375.0, 23.0, 50.0]])
    >>> per_step = watch.update(t, u, np.zeros((3, 5)), np.zeros((3, 5)))
    >>> watch.restarts, [(s["ready"], s["restarts"]) for s in per_step]
    (1, [(False, 0), (False, 0), (False, 1)])
    >>> per_step[1]["text"]
    'the atomizer is off (below 50 mA): not ready to print'
    >>> _ = watch.update([3.0], [[0.0, 23.0, 50.0]], np.zeros((1, 5)), np.zeros((1, 5)))
    >>> _ = watch.update([4.0], [[375.0, 23.0, 50.0]], np.zeros((1, 5)), np.zeros((1, 5)))
    >>> watch.restarts  # the restart was the block's first step: counted once
    2
    """

    def __init__(self, settings: SettlingSettings | None = None):
        self.settings = settings or SettlingSettings.load()
        self.detector = SettlingDetector(self.settings)
        self.restarts = 0  # atomizer restarts seen in this print
        self._off = False

    def update(self, time_s, inputs, means, outputs) -> list[dict]:
        """Take committed steps: times (n,) [s], inputs (n, 3) [mA, sccm, sccm], filtered
        state means (n, 5), predicted outputs (n, 5). Returns the JSON-ready verdict as of
        each step (:meth:`SettlingDetector.status`, "ready" only from the second it was, and
        ``restarts``: the atomizer restarts so far)."""
        time_s = np.atleast_1d(np.asarray(time_s, dtype=float))
        current = np.atleast_2d(np.asarray(inputs, dtype=float))[:, 0]
        off_mA = self.settings.atomizer_off_mA
        restarts, self._off = atomizer_restarts(current, self._off, off_mA)
        # runs of steps, each begun by a restart or the block's start (a restart at step 0
        # begins the first run: one new detector, not two)
        cuts = [0, *(k for k in restarts if k > 0), len(time_s)]
        out: list[dict] = []
        for a, b in zip(cuts[:-1], cuts[1:]):
            if a in restarts:
                self.detector = SettlingDetector(self.settings)
                self.restarts += 1
            if b > a:
                self.detector.update(time_s[a:b], np.asarray(means)[a:b], np.asarray(outputs)[a:b])
            status = {**self.detector.status(), "restarts": self.restarts}
            for k in range(a, b):
                if current[k] < off_mA:  # NaN: not known to be off
                    out.append(atomizer_off(status, off_mA))
                elif status["ready"] and status["ready_at_s"] > time_s[k]:
                    out.append(not_ready_yet(status))
                else:
                    out.append(status)
        return out

    def status(self) -> dict:
        """The verdict now (:meth:`SettlingDetector.status`)."""
        return {**self.detector.status(), "restarts": self.restarts}


def not_ready_yet(status: dict) -> dict:
    """A step before the second its detector was ready at (same evidence, not ready)."""
    text = "not settled yet: " + status["text"].split(": ", 1)[-1]
    return {**status, "ready": False, "ready_at_s": None, "text": text}


def atomizer_off(status: dict, off_mA: float) -> dict:
    """A step with the atomizer off: not ready, whatever the line did before."""
    text = f"the atomizer is off (below {off_mA:g} mA): not ready to print"
    return {**status, "ready": False, "ready_at_s": None, "evidence": {}, "text": text}


def settling_time(time_s, means, outputs, settings: SettlingSettings | None = None) -> Readiness:
    """The batch verdict over a whole run (the same as feeding :class:`SettlingDetector`)."""
    return SettlingDetector(settings).update(time_s, means, outputs)


def settling_from_table(frames, settings: SettlingSettings | None = None) -> Readiness:
    """The verdict from ``ajtwin estimate``'s table read in chunks (DataFrames with
    ``time_s``, the state columns and the ``pred_`` columns); stops reading once ready."""
    states = list(STATE_NAMES)
    outputs = ["pred_" + name for name in OUTPUT_NAMES]
    detector = SettlingDetector(settings)
    for frame in frames:
        r = detector.update(
            frame["time_s"].to_numpy(float),
            frame[states].to_numpy(float),
            frame[outputs].to_numpy(float),
        )
        if r.ready:
            break
    return detector.readiness
