"""The model–machine mismatch guard: the twin never turns a misfit into silent nonsense.

When the packaged (or calibrated) model does not describe the machine, the EKF still
returns numbers: a line model 30 µm off drives d_a to 0.2 µm, gauges reading 8 % high
appear as a 0.15 µm nozzle deposit from the first minute. This guard reads one run of
the twin and says, per second and for the print, whether the model fits:

* **physical range** — any filtered state outside :class:`~ajtwin.model.limits.StateLimits`;
* **persistent innovation bias** — the rolling mean of an output's normalised
  innovations e = ν/√S over ``bias_window_s`` beyond ``bias_sigma`` (white, well-modelled
  innovations average to ~0; the twin's process noise absorbs a fault only slowly, a
  structural misfit never);
* **windowed NIS far from 1** — the rolling mean of NIS per measured output outside
  [``nis_low``, ``nis_high``];
* **start surprise** — in the first ``start_window_s`` a state the start prior holds
  (fill, deposits) moves more than ``start_sigma`` prior σ: a clean nozzle cannot clog
  in a minute, so pressures that say so are a gauge or plumbing misfit.

On a print that begins with the atomizer's run-in (the record says when it was switched on)
the seconds before the twin says ready to print are no evidence on the outputs a mist
building up moves, and Q_m's level waits for an EM update learned after it
(:func:`without_run_in`, :func:`run_in_level_s`).

Each finding names the output(s)/state(s) and the likely fix. Thresholds:
``data/mismatch.toml`` (with how they were set). A mismatch is not a fault of the
print: :func:`relabel_events` marks anomaly events it explains.

Examples
--------
>>> import numpy as np
>>> e = np.zeros((400, 5)); e[:, 2] = 1.5      # P_c persistently 1.5 σ above the model
>>> s = assess(np.arange(400.0), np.tile([3.5, 1, 0, 0.01, 4.6e-7], (400, 1)), e,
...            np.full(400, 5.0), np.full(400, 5))
>>> s.mismatch, s.outputs
(True, ['carrier_pressure_Pa'])
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ajtwin import units
from ajtwin.apps.detection.settling import settling_time, switched_on_s
from ajtwin.apps.detection.statistics import normalised_innovations
from ajtwin.config import packaged_toml
from ajtwin.estimation.filters import DEFAULT_SCALING
from ajtwin.model import load_parameters
from ajtwin.model.limits import StateLimits
from ajtwin.model.names import OUTPUT_NAMES, OUTPUT_WORDS, STATE_NAMES, STATE_WORDS

#: Likely fix per output / state.
FIXES = {
    "linewidth_um": "commission the machine (line-model offset/gain) or recalibrate the camera "
    "(µm per pixel)",
    "overspray_um": "commission the machine (line-model offset/gain) or recalibrate the camera "
    "(µm per pixel)",
    "carrier_pressure_Pa": "check the carrier pressure gauge (zero and span) and the carrier "
    "line, then commission the machine",
    "sheath_pressure_Pa": "check the sheath pressure gauge (zero and span) and the sheath line, "
    "then commission the machine",
    "material_flow_mL_s": "recalibrate the height-profile CNN / platen speed (Q_m gain) or "
    "commission the machine",
    "droplet_diameter_um": "commission the machine: the line model does not fit (d_a absorbs it)",
    "aerosol_fraction": "commission the machine: Q_m or the line model does not fit",
    "vial_volume_mL": "check the vial fill entered for this print",
    "tube_deposition_um": "check the pressure gauges or commission the machine",
    "nozzle_deposition_um": "check the pressure gauges (zero and span) or commission the "
    "machine; if the nozzle was not cleaned, record it (`ajtwin machine maintain`)",
    "nis": "commission the machine (the noise and output model do not fit its data)",
}


def load_guard_settings() -> dict:
    """The guard's thresholds with their provenance (``data/mismatch.toml`` ``[guard]``)."""
    return packaged_toml("data/mismatch.toml")["guard"]


@dataclass
class MismatchStatus:
    """The guard's verdict on one print (JSON-friendly via :meth:`to_dict`)."""

    mismatch: bool
    first_s: float | None  # time of the first finding
    outputs: list = field(default_factory=list)  # outputs that do not fit
    states: list = field(default_factory=list)  # states out of range / surprising
    reasons: list = field(default_factory=list)  # one sentence per finding
    fixes: list = field(default_factory=list)
    message: str = "the model fits this machine"
    flags: np.ndarray = None  # (T,) bool: a finding holds at this second
    # states named only by the start surprise: they explain alarms of the start window,
    # not a fault that begins later on the same outputs (a clog stays a clog)
    start_states: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """The verdict as plain JSON-friendly values (without the per-second ``flags``)."""
        out = asdict(self)
        out.pop("flags")
        return out


def _rolling_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over ``window`` rows ignoring NaN (NaN where nothing was measured).

    A (T, m) array is taken a column at a time: the sums' temporaries are then (T,) each,
    not (T, m) (a week's print: ~35 MB instead of ~170 MB at the guard's end pass)."""
    values = np.asarray(values, dtype=float)
    if values.ndim > 1:
        out = np.empty(values.shape)
        for j in range(values.shape[1]):
            out[:, j] = _rolling_mean(values[:, j], window)
        return out
    finite = np.isfinite(values)
    csum = np.zeros(len(values) + 1)
    np.cumsum(np.where(finite, values, 0.0), out=csum[1:])
    ccount = np.zeros(len(values) + 1)
    np.cumsum(finite, out=ccount[1:])
    lo = np.maximum(np.arange(1, len(values) + 1) - int(window), 0)
    total = csum[1:] - csum[lo]
    count = ccount[1:] - ccount[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


class GuardInputs:
    """The guard's per-second inputs of a print taken a chunk at a time (18 numbers a
    second), for :func:`assess` once the print has ended.

    Examples
    --------
    >>> g = GuardInputs()
    >>> g.add(np.arange(3.0), np.zeros((3, 5)), np.zeros((3, 5)), np.ones(3), np.ones(3),
    ...       np.ones((3, 5)))
    >>> g.n
    3
    """

    KEYS = ("time_s", "means", "e", "nis", "n_measured", "stds")

    def __init__(self):
        self._parts: dict[str, list] = {k: [] for k in self.KEYS}
        self.n = 0

    def add(self, time_s, means, e, nis, n_measured, stds) -> None:
        """A chunk's steps: times (n,), filtered means (n, 5), normalised innovations
        (n, 5), NIS (n,), outputs measured (n,), the states' σ (n, 5) or None (not known)."""
        for key, value in zip(self.KEYS, (time_s, means, e, nis, n_measured, stds), strict=True):
            self._parts[key].append(None if value is None else np.asarray(value, dtype=float))
        self.n += len(time_s)

    def take(self) -> dict:
        """The steps added, each input joined over the chunks (None: not given), and let go;
        the chunks are joined one input at a time (the inputs are not held twice)."""
        whole = {}
        for key in self.KEYS:
            parts = self._parts.pop(key)
            whole[key] = None if any(p is None for p in parts) else np.concatenate(parts)
            parts.clear()
        self._parts = {k: [] for k in self.KEYS}
        self.n = 0
        return whole

    def assess(self, **kwargs) -> MismatchStatus:
        """:func:`assess` over the steps added (``kwargs``: its keywords), which are let go."""
        whole = self.take()
        n_measured = whole.pop("n_measured")
        return assess(
            whole.pop("time_s"),
            whole.pop("means"),
            whole.pop("e"),
            whole.pop("nis"),
            n_measured,
            stds=whole.pop("stds"),
            **kwargs,
        )


def assess(
    time_s,
    means,
    normalised_innovations,
    nis,
    n_measured,
    *,
    start_mean=None,
    start_cov=None,
    limits=None,
    settings: dict | None = None,
    level_learned_s: float | None = None,
    stds=None,
) -> MismatchStatus:
    """Run the guard's four tests (module docstring) over one print.

    Parameters
    ----------
    time_s : (T,) ; means : (T, 5) filtered states (display units)
    normalised_innovations : (T, 5) e = ν/√S (NaN where not measured)
    nis, n_measured : (T,)
    start_mean, start_cov : (5,), (5, 5), optional
        The print's start prior (for the start-surprise test).
    limits : StateLimits, optional
        Default: ``data/state_limits.toml`` with the packaged parameters.
    level_learned_s : float, optional
        Time (same clock as ``time_s``) from which the twin has learned the print's level of
        the ``level_learned_outputs`` (``data/mismatch.toml``: Q_m, whose level is the
        print's atomizer efficiency, learned only by EM's θ_φA). Their bias test reads only
        samples from then on. None: from the warm-up (the twin cannot learn the level, so a
        level offset is a misfit).
    stds : (T, 5), optional
        The states' σ (display units): with them a deposit estimated below zero by more
        than its noise (``negative_deposit_*`` in ``data/mismatch.toml``) is a finding.
    """
    g = settings or load_guard_settings()
    t = np.asarray(time_s, dtype=float)
    learned = None if level_learned_s is None else float(level_learned_s) - float(t[0])
    t = t - t[0]
    found = _Findings(t, t >= float(g["warmup_s"]))
    inputs = (means, normalised_innovations, nis, n_measured, stds)
    start_only = _all_findings(found, inputs, g, limits, learned, (start_mean, start_cov))
    return _verdict(found, start_only)


def _all_findings(found, inputs, g: dict, limits, learned, start) -> set:
    """The guard's tests over the rows of ``found`` (means, e, NIS, outputs measured, σ or
    None); the names the start surprise alone found."""
    means, e, nis, n_measured, stds = inputs
    means = np.asarray(means, dtype=float)
    e = np.asarray(e, dtype=float)
    _state_range_findings(found, means, limits or StateLimits.load(load_parameters()))
    if stds is not None:
        _negative_deposit_findings(found, means, np.asarray(stds, dtype=float), g)
    _output_bias_findings(found, _output_bias(found.t, e, g, learned), np.isfinite(e), g)
    _nis_findings(found, nis, n_measured, g)
    if start[0] is not None and start[1] is not None:
        return _start_surprise_findings(found, means, start[0], start[1], g)
    return set()


class ChunkedGuard:
    """The guard (:func:`assess`) over a print taken a chunk at a time, with the same
    verdict as over the whole print and memory flat in its length.

    Each test is a trailing window of ``bias_window_s`` or ``nis_window_s`` rows or a test
    of one row, so a chunk is judged with the last ``max(bias_window_s, nis_window_s)`` rows
    before it carried over (the windows then see what they would see over the whole print);
    a finding keeps its first second over all chunks. Rows wait (unjudged) until the print
    has run ``nis_window_s``: a shorter print's NIS is judged at its end (:func:`assess`'s
    short-print rule). ``level_learned_s`` must be known from the start (the time of EM's
    first update, :func:`assess`); the ``flags`` of the verdict are 1 byte a second.

    Examples
    --------
    >>> e = np.zeros((400, 5)); e[:, 2] = 1.5
    >>> guard = ChunkedGuard()
    >>> for k in range(0, 400, 150):
    ...     guard.add(np.arange(k, min(k + 150, 400.0)), np.tile([3.5, 1, 0, 0.01, 4.6e-7],
    ...               (len(e[k:k + 150]), 1)), e[k:k + 150], np.full(len(e[k:k + 150]), 5.0),
    ...               np.full(len(e[k:k + 150]), 5))
    >>> guard.finish().outputs
    ['carrier_pressure_Pa']
    """

    def __init__(
        self,
        *,
        start_mean=None,
        start_cov=None,
        limits=None,
        settings: dict | None = None,
        level_learned_s: float | None = None,
    ):
        self._g = settings or load_guard_settings()
        self._limits = limits or StateLimits.load(load_parameters())
        self._start = (start_mean, start_cov)
        self._level_learned_s = level_learned_s
        self._lookback = max(int(self._g["bias_window_s"]), int(self._g["nis_window_s"]))
        self._tail: dict | None = None  # the last judged rows, carried over
        self._pending = GuardInputs()
        self._t0: float | None = None
        self._judged = 0  # rows judged so far
        self._items: dict = {}  # a test's place in the run → its first finding
        self._start_only: set = set()
        self._flags: list = []

    def learn_level_from(self, level_learned_s: float | None) -> None:
        """From when the twin holds the print's atomizer level, once it is known later than
        at the start (a run-in's settled EM update, :func:`settled_level_s`): the rows not
        judged yet are judged with it. Rows judged before it was known must have been judged
        with a level not learned (inf)."""
        self._level_learned_s = level_learned_s

    def add(self, time_s, means, e, nis, n_measured, stds=None) -> None:
        """A chunk's steps (as :meth:`GuardInputs.add`; ``stds`` None: no deposit test)."""
        if len(time_s) == 0:
            return
        if self._t0 is None:
            self._t0 = float(time_s[0])
        self._pending.add(time_s, means, e, nis, n_measured, stds)
        if float(time_s[-1]) - self._t0 >= float(self._g["nis_window_s"]):
            self._judge()

    def _judge(self) -> None:
        """Judge the waiting rows with the carried-over ones before them."""
        new = self._pending.take()
        carried = 0 if self._tail is None else len(self._tail["time_s"])
        rows = new if self._tail is None else {
            k: None if new[k] is None else np.concatenate([self._tail[k], new[k]])
            for k in new
        }  # fmt: skip
        t = rows["time_s"] - self._t0
        owned = np.arange(len(t)) >= carried
        found = _Findings(t, owned & (t >= float(self._g["warmup_s"])))
        learned = self._level_learned_s
        learned = None if learned is None else float(learned) - self._t0
        inputs = tuple(rows[k] for k in GuardInputs.KEYS[1:])
        self._start_only |= _all_findings(found, inputs, self._g, self._limits, learned,
                                          self._start)  # fmt: skip
        offset = self._judged - carried
        for place, (k, kind, name, sentence, t_k) in zip(found.places, found.items, strict=True):
            self._items.setdefault(place, (k + offset, kind, name, sentence, t_k))
        self._flags.append(found.flags[carried:])
        self._judged += len(t) - carried
        self._tail = {
            k: None if v is None else v[-self._lookback :] for k, v in rows.items()
        }  # fmt: skip

    def finish(self) -> MismatchStatus:
        """The verdict over all the steps added (as :func:`assess` over the whole print)."""
        if self._pending.n:
            self._judge()
        found = _Findings(np.zeros(0), np.zeros(0, dtype=bool))
        found.items = list(self._items.values())
        found.flags = np.concatenate(self._flags) if self._flags else np.zeros(0, dtype=bool)
        return _verdict(found, self._start_only)


class _Findings:
    """The guard's findings over one print: (first index, kind, name, sentence) each, and
    the seconds at which any holds (after the warm-up ``active``)."""

    def __init__(self, t: np.ndarray, active: np.ndarray):
        self.t = t
        self.active = active
        self.flags = np.zeros(len(t), dtype=bool)
        self.items: list[tuple[int, str, str, str, float]] = []
        self.places: list[int] = []  # each finding's test: its place in the run of tests
        self._calls = 0

    def first(self, mask) -> int | None:
        """The first active index where ``mask`` holds (None: nowhere)."""
        hits = np.flatnonzero(mask & self.active)
        return int(hits[0]) if hits.size else None

    def add(self, mask, kind: str, name: str, sentence) -> int | None:
        """Record a finding where ``mask`` holds; ``sentence(k)`` says it at its first index."""
        k = self.first(mask)
        self._calls += 1
        if k is not None:
            self.flags |= mask & self.active
            self.items.append((k, kind, name, sentence(k), float(self.t[k])))
            self.places.append(self._calls)
        return k


def _state_range_findings(found: _Findings, means: np.ndarray, limits) -> None:
    """A state outside its physical range (``data/state_limits.toml``)."""
    inside = limits.inside(means)
    for i, name in enumerate(STATE_NAMES):
        found.add(
            ~inside[:, i],
            "state",
            name,
            lambda k: f"{limits.violations(means[k])[0]} at {found.t[k]:.0f} s",
        )


def _negative_deposit_findings(found: _Findings, means, stds, g: dict) -> None:
    """A deposit below zero by more than its own noise.

    A deposit is never negative: an estimate below 0 by more than its own noise means the
    pressures are read through a model that does not fit (a gauge's zero or span, a line's
    resistance), the signature of an uncommissioned machine whose deviations mimic other
    states (held-out alt machines 1029, 1135: ΔR_N −42 / −76 nm at σ 0.6 nm).
    """
    floor = float(g.get("negative_deposit_floor_um", np.inf))
    k_sigma = float(g.get("negative_deposit_sigma", np.inf))
    for name in ("tube_deposition_um", "nozzle_deposition_um"):
        i = STATE_NAMES.index(name)
        found.add(
            means[:, i] < -(floor + k_sigma * stds[:, i]),
            "state",
            name,
            lambda k, i=i, name=name: (
                f"{name} = {units.um_to_nm(means[k, i]):.1f} nm is below zero by "
                f"{-means[k, i] / max(stds[k, i], 1e-300):.0f} σ at {found.t[k]:.0f} s: a "
                "deposit cannot be negative"
            ),
        )


def _output_bias(t: np.ndarray, e: np.ndarray, g: dict, learned: float | None) -> np.ndarray:
    """Rolling mean of the normalised innovations (T, 5) over ``bias_window_s``, NaN where it
    is no evidence of a misfit.

    Before EM's first θ (``learned`` [s from the start]) the twin has no parameter for
    the print's own atomizer level (φ_A follows the generation model within seconds): a
    Q_m level offset then is the print-to-print variation the start prior allows, not a
    misfit; and a whole window after it neither (the θ update itself moves φ_A for tens
    of seconds). Outputs that read φ_A beside others (L_o) are not judged while Q_m says
    the level is off the same way.
    """
    window = int(g["bias_window_s"])
    if learned is None:
        return _rolling_mean(e, window)
    level_columns = [OUTPUT_NAMES.index(name) for name in g.get("level_learned_outputs", [])]
    # a column at a time (no copy of the whole e), the level's before EM's first θ as NaN
    bias = np.empty(e.shape)
    for j in range(e.shape[1]):
        column = np.where(t < learned, np.nan, e[:, j]) if j in level_columns else e[:, j]
        bias[:, j] = _rolling_mean(column, window)
    unlearned = t < learned + float(g["bias_window_s"])
    bias[np.ix_(unlearned, level_columns)] = np.nan
    level = _rolling_mean(e[:, OUTPUT_NAMES.index("material_flow_mL_s")], window)
    level_evidence = float(g.get("level_evidence_fraction", 0.5)) * float(g["bias_sigma"])
    for name in g.get("level_explained_outputs", []):
        j = OUTPUT_NAMES.index(name)
        same_way = np.sign(np.nan_to_num(bias[:, j])) == np.sign(np.nan_to_num(level))
        explained = unlearned & same_way & (np.abs(np.nan_to_num(level)) >= level_evidence)
        bias[explained, j] = np.nan
    return bias


def _measured_seconds(n_measured, window: int) -> np.ndarray:
    """(T,) seconds with at least one measured output in the trailing ``window`` [s]."""
    measured = (np.asarray(n_measured, dtype=float) > 0).astype(float)
    return _rolling_mean(measured, window) * np.minimum(np.arange(1, measured.size + 1), window)


def _output_bias_findings(found: _Findings, bias: np.ndarray, measured, g: dict) -> None:
    """An output persistently above or below the model (a full window of evidence, or the
    print so far after its own minimum); seconds where the output was not measured (a logger
    gap the twin predicts through, a job print's seconds with no trace under the camera or
    its inspection pass) are no evidence for it."""
    min_evidence = float(g.get("bias_min_evidence_s", g["warmup_s"]))
    window = int(g["bias_window_s"])
    for j, name in enumerate(OUTPUT_NAMES):
        evidence = (found.t >= min_evidence) & (
            _measured_seconds(measured[:, j], window) >= min_evidence
        )
        found.add(
            evidence & (np.abs(np.nan_to_num(bias[:, j])) > float(g["bias_sigma"])),
            "output",
            name,
            lambda k, j=j, name=name: (
                f"{name} persistently {'above' if bias[k, j] > 0 else 'below'} the model "
                f"({bias[k, j]:+.2f} σ mean over {int(g['bias_window_s'])} s) from "
                f"{found.t[k]:.0f} s"
            ),
        )


def _nis_findings(found: _Findings, nis, n_measured, g: dict) -> None:
    """The mean NIS per output over ``nis_window_s`` outside [``nis_low``, ``nis_high``]."""
    t = found.t
    counts = np.asarray(n_measured, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_output = np.where(counts > 0, np.asarray(nis, dtype=float) / counts, np.nan)
    rolling_nis = _rolling_mean(per_output[:, None], int(g["nis_window_s"]))[:, 0]
    full = t >= min(float(g["nis_window_s"]), max(t[-1], 0.0))
    full &= _measured_seconds(n_measured, int(g["nis_window_s"])) >= float(
        g.get("bias_min_evidence_s", g["warmup_s"])
    )
    mask = full & ((rolling_nis < float(g["nis_low"])) | (rolling_nis > float(g["nis_high"])))
    found.add(
        mask,
        "nis",
        "nis",
        lambda k: (
            f"mean NIS per output {rolling_nis[k]:.2f} over {int(g['nis_window_s'])} s "
            f"(1 = consistent; allowed {g['nis_low']}–{g['nis_high']}) at {t[k]:.0f} s"
        ),
    )


def _start_surprise_findings(found: _Findings, means, start_mean, start_cov, g: dict) -> set:
    """A state that moves many prior σ within ``start_window_s`` of the start; the names.

    A carried-over start has a tight prior (the previous print's end) and the filter
    re-converges d_a and φ_A in the first minute, moving the deposits by ~1 nm through
    their correlation: only a move beyond the floor is a misfit's signature.
    """
    floor = np.array([float(g.get("start_floor", {}).get(name, 0.0)) for name in STATE_NAMES])
    var = np.maximum(np.diag(np.asarray(start_cov, float)), 1e-300) + floor**2
    window = found.t <= float(g["start_window_s"])
    # z over the start window's seconds only (beyond it no finding is looked for)
    z = np.zeros(means.shape)
    z[window] = np.abs(means[window] - np.asarray(start_mean, float)) / np.sqrt(var)
    start_only = set()
    for name in g["start_states"]:
        i = STATE_NAMES.index(name)
        k = found.add(
            window & (z[:, i] > float(g["start_sigma"])),
            "state",
            name,
            lambda k, i=i, name=name: (
                f"{name} moved {z[k, i]:.1f} prior σ within {found.t[k]:.0f} s of the start "
                f"({start_mean[i]:.4g} → {means[k, i]:.4g}): faster than the machine "
                "can change"
            ),
        )
        if k is not None:
            start_only.add(name)
    return start_only


def _verdict(found: _Findings, start_only: set) -> MismatchStatus:
    """The findings as the guard's status: first time, outputs, states, reasons, fixes."""
    if not found.items:
        return MismatchStatus(False, None, flags=found.flags)
    findings = sorted(found.items, key=lambda f: f[0])
    outputs = sorted({f[2] for f in findings if f[1] == "output"}, key=OUTPUT_NAMES.index)
    states = sorted({f[2] for f in findings if f[1] == "state"}, key=STATE_NAMES.index)
    fixes = list(dict.fromkeys(FIXES[f[2]] for f in findings))
    reasons = [f[3] for f in findings]
    message = (
        "model–machine mismatch: "
        + "; ".join(reasons[:3])
        + (f" (+{len(reasons) - 3} more)" if len(reasons) > 3 else "")
        + ". Likely fix: "
        + "; ".join(fixes[:2])
    )
    # a state also out of range is a misfit for the whole print, not only at its start
    out_of_range = {f[2] for f in findings if f[1] == "state" and "physical range" in f[3]}
    start_states = sorted(start_only - out_of_range, key=STATE_NAMES.index)
    return MismatchStatus(
        True,
        findings[0][4],
        outputs,
        states,
        reasons,
        fixes,
        message,
        found.flags,
        start_states,
    )


def assess_run(run, record, settings: dict | None = None) -> MismatchStatus:
    """:func:`assess` on a :class:`~ajtwin.estimation.twin.TwinRun` and its record (the
    measurements the filter used: on a job print, filed at their print times); a print that
    begins with the atomizer's run-in (the record's ``atomizer_switched_on_s``) is judged
    without it (:func:`without_run_in`, :func:`settled_level_s`)."""

    f = run.filtered
    measured = getattr(run, "measurements", None)
    e = normalised_innovations(
        record.outputs if measured is None else measured,
        np.asarray(f.predicted_outputs),
        np.asarray(f.innovation_variances),
    )
    run_in, ready = run_in_ready_s(run, record)
    e = without_run_in(run.time_s, e, run_in, ready, settings)
    return assess(
        run.time_s,
        run.means,
        e,
        np.asarray(f.nis),
        np.asarray(f.n_measured),
        start_mean=run.start_mean,
        start_cov=run.start_cov,
        settings=settings,
        level_learned_s=settled_level_s(run, run_in, ready),
        stds=run.stds,
    )


def first_em_update_s(run, window_from_s: float | None = None) -> float | None:
    """When the twin's first EM update took effect (None: EM did not run): from then on θ_φA
    holds the print's atomizer level, so Q_m's level is the model's to explain.
    ``window_from_s``: the first update whose window began at or after then (inf: none)."""
    history = getattr(run, "theta_history", None)
    if history is None or len(history) == 0 or "time_s" not in history:
        return None
    if window_from_s is not None:
        history = history[history["window_start_s"].to_numpy(float) >= window_from_s]
        if len(history) == 0:
            return np.inf
    return float(history["time_s"].iloc[0])


def run_in_ready_s(run, record) -> tuple[bool, float | None]:
    """(whether the print begins with the atomizer's run-in — the record's
    ``atomizer_switched_on_s`` —, when the twin said ready to print after it: None, not in
    this print) over a whole run (:func:`~ajtwin.apps.detection.settling.settling_time`)."""
    start = switched_on_s(getattr(record, "meta", None))
    if start is None:
        return False, None
    t = np.asarray(run.time_s, dtype=float)
    after = t >= start
    f = run.filtered
    verdict = settling_time(
        t[after], np.asarray(f.means)[after], np.asarray(f.predicted_outputs)[after]
    )
    return True, verdict.ready_at_s


def settled_level_s(run, run_in: bool, ready_s: float | None) -> float | None:
    """:func:`run_in_level_s` from a run's θ history (its EM updates and their windows)."""
    settled = None if ready_s is None else first_em_update_s(run, ready_s)
    return run_in_level_s(first_em_update_s(run), settled, run_in, ready_s)


def without_run_in(time_s, e, run_in: bool, ready_s: float | None, settings: dict | None = None):
    """The normalised innovations (T, 5) the guard may read of a print that begins with the
    atomizer's run-in (``run_in``): the outputs a mist building up moves (``run_in_outputs``
    of ``data/mismatch.toml``: the line and Q_m, not the pressures) as not measured before the
    twin said ready to print at ``ready_s`` (None: not yet — all of them). Seconds not measured
    are no evidence of a misfit (:func:`assess`). ``e`` itself is returned when ``run_in`` is
    false.

    >>> e = np.ones((4, 5))
    >>> without_run_in(np.arange(4.0), e, True, 2.0)[:, [0, 2, 4]].tolist()
    [[nan, 1.0, nan], [nan, 1.0, nan], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    """
    if not run_in:
        return e
    g = settings or load_guard_settings()
    e = np.array(e, dtype=float)
    before = np.asarray(time_s, dtype=float) < (np.inf if ready_s is None else ready_s)
    columns = [OUTPUT_NAMES.index(name) for name in g["run_in_outputs"]]
    e[np.ix_(before, columns)] = np.nan
    return e


def run_in_level_s(first_s, settled_s, run_in: bool, ready_s: float | None) -> float | None:
    """When the twin holds the print's atomizer level: EM's first θ (``first_s``; None: no
    EM); on a print that begins with the atomizer's run-in (``run_in``) the first θ learned
    over a window that began once the twin said ready to print at ``ready_s`` (``settled_s``;
    inf: not ready, or no such update in this print).

    Why: the run-in's mist builds up for 5-15 min, and the θ_φA that EM learns over a window
    of it holds a level the atomizer has since left: Q_m then reads above the twin until a
    settled window has been learned (virtual start-ups, seeds 1-10: +0.8…+1.7σ over 300 s
    from the first level test at 7 min to 16-18 min, on every one).

    >>> run_in_level_s(120.0, 900.0, True, 475.0), run_in_level_s(120.0, 900.0, False, 475.0)
    (900.0, 120.0)
    >>> run_in_level_s(120.0, None, True, None)
    inf
    """
    if first_s is None or not run_in:
        return first_s
    if ready_s is None or settled_s is None or not np.isfinite(settled_s):
        return np.inf
    return max(float(first_s), float(settled_s))


def data_share(filtered, carry: dict | None = None) -> np.ndarray:
    """(T, 5) how much of each state's information came from this print's data.

    share_k = 1 − P_{k|k} / Π_k per state, where Π_k is the variance the start prior
    alone would have at k: the filter's own recursion without any measurement,
    Π_0 = P_{0|−1}, Π_{k+1} = F_k Π_k F_kᵀ + Q_k, with F_k the filter's transition
    Jacobians and Q_k = P_{k+1|k} − F_k P_{k|k} F_kᵀ its process noise (recovered exactly
    from its own covariances, so the shares follow whatever tuning the twin used).
    1: the data fixed the state (d_a, φ_A, ΔR_N on a print with camera and gauges);
    0: the band is the prior's, carried by the model (ΔR_T: ≤ 1e-3 µm of deposit moves
    P_c by < 1 Pa; V_l, a consider state that only follows the fill and the draw).
    Computed in the filter's scaled coordinates (the states span 15 orders of magnitude).
    ``carry`` (a dict, empty at a print's start): a run taken in chunks, ``filtered`` one of
    them; the recursion goes on from the previous chunk's last step and is kept for the next.

    >>> from types import SimpleNamespace
    >>> one = np.eye(5)[None].repeat(2, 0)
    >>> f = SimpleNamespace(covariances=one * 0.5, predicted_covariances=one * 1.0,
    ...                     transition_jacobians=one)       # F = I, Q = 1 − 0.5 = 0.5
    >>> data_share(f)[:, 0].tolist()                        # 1 − 0.5/1, 1 − 0.5/(1 + 0.5)
    [0.5, 0.6666666666666667]
    """

    scale = np.asarray(DEFAULT_SCALING.state, dtype=float)
    outer = np.outer(scale, scale)
    post = np.asarray(filtered.covariances, dtype=float) / outer
    pred = np.asarray(filtered.predicted_covariances, dtype=float) / outer
    jac = np.asarray(filtered.transition_jacobians, dtype=float)
    n = len(post)
    priors = np.empty_like(post)
    prior = pred[0].copy()
    if carry:  # the previous chunk's last step: Π_0 = F Π F^T + (P_{0|−1} − F P F^T)
        f = carry["jac"]
        prior = f @ (carry["prior"] - carry["post"]) @ f.T + pred[0]
    for k in range(n):
        priors[k] = prior
        if k + 1 < n:  # Π_{k+1} = F Π F^T + (P_{k+1|k} − F P_{k|k} F^T), one product
            prior = jac[k] @ (prior - post[k]) @ jac[k].T + pred[k + 1]
    if carry is not None and n:
        carry.update(prior=prior, post=post[-1], jac=jac[-1])
    diagonal = np.arange(post.shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        share = 1.0 - post[:, diagonal, diagonal] / priors[:, diagonal, diagonal]
    return np.clip(np.nan_to_num(share, nan=0.0), 0.0, 1.0)


def determined_states(share, settings: dict | None = None) -> dict:
    """State → {"data_share": share at the print's end, "determined": share ≥
    ``undetermined_share`` (data/mismatch.toml)}: which bands this print's data set."""
    g = settings or load_guard_settings()
    end = np.asarray(share, dtype=float)[-1]
    threshold = float(g["undetermined_share"])
    return {
        name: {"data_share": round(float(end[i]), 4), "determined": bool(end[i] >= threshold)}
        for i, name in enumerate(STATE_NAMES)
    }


MISMATCH_CAUSE = "model_machine_mismatch"

_SHORT = dict(zip(OUTPUT_NAMES, ("L_w", "L_o", "P_c", "P_s", "Q_m"), strict=True))
#: outputs whose misfit a state's misfit stands for
_STATE_OUTPUTS = {
    "droplet_diameter_um": {"L_w", "L_o"},
    "aerosol_fraction": {"L_w", "L_o", "Q_m"},
    "vial_volume_mL": {"Q_m"},
    "tube_deposition_um": {"P_c", "P_s"},
    "nozzle_deposition_um": {"P_c", "P_s"},
}


def _mismatch_channels(status: MismatchStatus) -> set:
    """Outputs on which the misfit shows for the whole print (start-only findings excluded)."""
    channels = {_SHORT[o] for o in status.outputs}
    for state in status.states:
        if state in (status.start_states or ()):
            continue
        channels |= _STATE_OUTPUTS.get(state, set())
    return channels


def _event_channels(event) -> set:
    """Outputs an anomaly event's detectors fired on (``"cusum+ P_c"``, ``"P_c+P_s"``)."""
    channels = set()
    for detector in event.detectors:
        for short in _SHORT.values():
            if short in detector:
                channels.add(short)
    return channels


def mismatch_line(guard: dict) -> str:
    """One short line in words for a guard's verdict (:meth:`MismatchStatus.to_dict`, as
    stored with a print): what does not fit, that it is not a fault, and what to do. The
    full reasons stay in ``guard["message"]`` (shown on demand).

    >>> mismatch_line({"outputs": ["carrier_pressure_Pa"], "states": ["nozzle_deposition_um"]})
    ... # doctest: +NORMALIZE_WHITESPACE
    'model does not fit this machine (carrier pressure, nozzle deposit): not a fault;
     commission the machine'
    >>> mismatch_line({"outputs": [], "states": []})
    'model does not fit this machine: not a fault; commission the machine'
    """
    words = dict(zip(OUTPUT_NAMES, OUTPUT_WORDS, strict=True))
    words.update(zip(STATE_NAMES, STATE_WORDS, strict=True))
    named = [words.get(n, n) for n in [*(guard.get("outputs") or []), *(guard.get("states") or [])]]
    what = f" ({', '.join(dict.fromkeys(named))})" if named else ""
    return f"model does not fit this machine{what}: not a fault; commission the machine"


def relabel_events(events: list, status: MismatchStatus) -> list:
    """Anomaly events explained by a mismatch get the cause ``model_machine_mismatch``.

    An event is explained when the guard's first finding came no later than the event's
    onset and either the event begins in the guard's start window or its detectors fired
    on an output the mismatch names: the detectors then see the misfit, not a new fault.
    A fault that begins later on other outputs, or on a machine that fitted, keeps its
    label (a clog stays a clog).
    """
    if not status.mismatch or status.first_s is None:
        return events
    g = load_guard_settings()
    # a misfit found in the start window was there from the start
    start = float(g["warmup_s"]) + float(g["start_window_s"])
    misfit = _mismatch_channels(status)
    out = []
    for ev in events:
        found_first = status.first_s <= max(float(ev.onset_s), start) + 1.0
        # at the start every alarm is the misfit; later only alarms on the misfit outputs
        same_outputs = bool(_event_channels(ev) & misfit)
        explained = found_first and (float(ev.onset_s) <= start or same_outputs)
        if explained and ev.cause != MISMATCH_CAUSE:
            ev.evidence = {**ev.evidence, "relabelled_from": ev.cause}
            ev.cause = MISMATCH_CAUSE
            ev.description = mismatch_line(status.to_dict())
        out.append(ev)
    return out
