"""The part quality map: which traces of a part are out of tolerance, and how likely.

The twin runs over the print as it ran (the camera's frames filed at their print times,
:func:`smoothed_run`); its smoothed states give the line printed at any time τ and
platen speed ν (:func:`line_at`, the twin's own
:func:`ajtwin.estimation.part_line.line_at`, model reference §5, §12):

    L(τ) = g(x̂(τ), u(τ), ν),   σ²(τ) = diag(H P(τ) Hᵀ) + (L ln(ν_ref/ν))² σ_b²,   H = ∂g/∂x,

with x̂(τ), P(τ) the smoothed mean and covariance interpolated linearly between the 1 Hz
samples around τ (P with the calibration's share and the floor of never-seen states, as
the twin reports its states), u(τ) the inputs held over that second, g the output model
with the speed law and σ_b the law's own uncertainty (0 at ν_ref). On a job print the
law's exponents are first learnt from the camera's readings of the traces printed at each
speed (:func:`~ajtwin.estimation.line_speed_fit.teach_speed_law`): σ_b is then
what those readings leave, not the packaged bracket.

The job (:mod:`ajtwin.job`) says what was printed when: each stroke is cut into portions of
at most ``portion_mm`` (:meth:`ajtwin.job.Job.portions`) and each portion sampled along its
length, points at most ``step_mm`` apart, at the time the nozzle passed there and the
speed of the segment it was on. Dwells with the shutter open (the public programs wait
2 ms before each stroke moves) have no length and are not sampled. Rapid moves are not
strokes.

A portion's **probability of being out of tolerance** is that of its worst point,

    P_out = max_i P(L_w,i ∉ [lo, hi]),   L_w,i ~ N(μ_i, σ_i²),

i.e. Φ((lo − μ_i)/σ_i) + 1 − Φ((hi − μ_i)/σ_i) at the point where it is largest. Why the
worst point and not the portion's mean: a portion that crosses a limit part-way is out of
tolerance there, and its mean would hide it. Why that is the probability that the portion
leaves the tolerance: within a portion (1 mm is 0.5 s at 2 mm/s) the smoothed states move
far less than their σ, so the points' errors are almost fully correlated, and for fully
correlated points P(some point out) is exactly the largest single-point probability (in
general it is a lower bound). A portion is **flagged** when P_out ≥ ``flag_probability``
(default 0.5: more likely out than in).

The line is evaluated in one place, the twin's; everything here (portions, probability,
alarms, the report) is geometry and bookkeeping around it.

Examples
--------
>>> parse_tolerance("45±3")
Tolerance(low_um=42.0, high_um=48.0)
>>> parse_tolerance("42:48").target_um
45.0
>>> round(float(out_of_tolerance_probability(48.0, 1.0, Tolerance(42.0, 48.0))), 3)
0.5
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.special import ndtr

from ajtwin import units
from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.causes import alarm_sentence
from ajtwin.estimation.line_speed_fit import teach_speed_law
from ajtwin.estimation.part_line import interpolation
from ajtwin.estimation.part_line import line_at as line_from_states
from ajtwin.estimation.print_time import is_job_record
from ajtwin.estimation.twin import Twin
from ajtwin.model.names import STATE_NAMES

#: The strokes.csv columns, in order (one row a stroke portion).
PORTION_COLUMNS = (
    "feature",
    "stroke",
    "portion",
    "repetition",
    "base_stroke",
    "from_x_mm",
    "from_y_mm",
    "to_x_mm",
    "to_y_mm",
    "length_mm",
    "printed_from_s",
    "printed_to_s",
    "speed_mm_s",
    "lw_mean_um",
    "lw_lo_um",
    "lw_hi_um",
    "lw_sd_um",
    "lo_mean_um",
    "lo_lo_um",
    "lo_hi_um",
    "p_out",
    "flagged",
)
#: Why a flagged portion is out (strokes.csv, after :data:`PORTION_COLUMNS`; empty for a
#: portion in tolerance): the alarm it was printed under (0: none) and its cause, and what
#: the twin reads as having moved the line — the state (or ``inputs``) whose change since
#: the first trace moved L_w most, its value then and at the portion (display units,
#: :data:`ajtwin.units.DISPLAY_UNITS`) and the change of L_w it made [µm].
CAUSE_COLUMNS = ("alarm", "cause", "driver", "driver_from", "driver_to", "driver_lw_um")
#: The strokes.csv columns of ``ajtwin job report``.
REPORT_COLUMNS = (*PORTION_COLUMNS, *CAUSE_COLUMNS)
#: Prefix of the per-candidate ΔL_w columns kept with a map's portions (not in strokes.csv).
CHANGE_PREFIX = "lw_change_"
#: Seconds of logged inputs whose median is "the inputs as set" at the reference.
INPUT_REFERENCE_S = 60
#: What a driver of ``inputs`` is called (the operator's or a controller's input change).
INPUTS_DRIVER = "inputs"
#: Default longest stroke portion [mm] and spacing of the sample points along it [mm].
PORTION_MM = 1.0
STEP_MM = 0.1
#: Default probability from which a portion is flagged.
FLAG_PROBABILITY = 0.5


class MapSettings(NamedTuple):
    """How a part is cut, sampled and judged (module docstring).

    Attributes
    ----------
    portion_mm : float
        Longest stroke portion [mm] (default :data:`PORTION_MM`).
    step_mm : float
        Largest spacing of the sample points along a portion [mm] (default :data:`STEP_MM`).
    flag_probability : float
        A portion is flagged from this probability of being out of tolerance, in [0, 1]
        (default :data:`FLAG_PROBABILITY`).

    Examples
    --------
    >>> MapSettings(portion_mm=2.0)
    MapSettings(portion_mm=2.0, step_mm=0.1, flag_probability=0.5)
    """

    portion_mm: float = PORTION_MM
    step_mm: float = STEP_MM
    flag_probability: float = FLAG_PROBABILITY


#: The packaged way a part is cut, sampled and judged.
MAP_DEFAULTS = MapSettings()


# --------------------------------------------------------------------------- #
# The tolerance
# --------------------------------------------------------------------------- #


class Tolerance(NamedTuple):
    """The linewidth's tolerance band [µm]."""

    low_um: float
    high_um: float

    @property
    def target_um(self) -> float:
        """The middle of the band (what deviations are measured from) [µm]."""
        return 0.5 * (self.low_um + self.high_um)

    @property
    def text(self) -> str:
        """The band as an operator writes it, ``45±3 µm``."""
        half = 0.5 * (self.high_um - self.low_um)
        return f"{self.target_um:g}±{half:g} µm"


_NUMBER = r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*"


def parse_tolerance(text) -> Tolerance:
    """``"45±3"``, ``"45+-3"``, ``"45 +/- 3"`` or ``"42:48"`` (µm; a trailing ``um``/``µm``
    allowed) → :class:`Tolerance`. ValueError naming the text otherwise."""
    raw = str(text).strip()
    body = re.sub(r"\s*(?:µm|um)\s*$", "", raw)
    centred = re.fullmatch(_NUMBER + r"(?:±|\+-|\+/-)" + _NUMBER, body)
    ranged = re.fullmatch(_NUMBER + r":" + _NUMBER, body)
    if centred:
        target, half = float(centred.group(1)), float(centred.group(2))
        low, high = target - half, target + half
    elif ranged:
        low, high = float(ranged.group(1)), float(ranged.group(2))
    else:
        raise ValueError(
            f"cannot read the tolerance {raw!r}: write the target and half-width in µm as "
            "45±3 (or 45+-3), or the limits as 42:48"
        )
    if not (math.isfinite(low) and math.isfinite(high) and 0.0 < low < high):
        raise ValueError(
            f"tolerance {raw!r}: the limits must be positive widths with low < high "
            f"(got {low:g} to {high:g} µm)"
        )
    return Tolerance(low, high)


def out_of_tolerance_probability(mean, sd, tolerance: Tolerance):
    """P(L ∉ [lo, hi]) for L ~ N(mean, sd²), array-wise (sd = 0: 0 or 1)."""
    mean = np.asarray(mean, dtype=float)
    sd = np.asarray(sd, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        below = ndtr((tolerance.low_um - mean) / sd)
        above = 1.0 - ndtr((tolerance.high_um - mean) / sd)
    exact = ((mean < tolerance.low_um) | (mean > tolerance.high_um)).astype(float)
    return np.where(sd > 0, below + above, exact)


# --------------------------------------------------------------------------- #
# The line from the twin's states
# --------------------------------------------------------------------------- #


def smoothed_run(record, twin: Twin | None = None, start=None, progress=None, job=None):
    """The twin (EKF + EM, then RTS) over ``record`` as the print ran:
    :meth:`Twin.run` with ``smooth=True`` and, for a job print, its job.

    ``twin``: the machine's twin with its θ (default :meth:`Twin.default`); ``start``: the
    start (mean, cov) (default: the initial-state fit); ``job``: the job as printed
    (:func:`ajtwin.estimation.print_time.job_as_printed`) — on a job print (a format-2
    record with the job columns) the camera's frames are filed at their print times with
    the speeds and the horizon the program gives; a record without the job columns runs
    as before (its frames at their row times). Returns the
    :class:`~ajtwin.estimation.twin.TwinRun`.
    """
    twin = twin or Twin.default()
    printed = job if job is not None and is_job_record(record) else None
    return twin.run(record, start=start, smooth=True, progress=progress, job=printed)


def line_at(run, times_s, speeds_mm_s, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """The line printed at times τ [s] and platen speeds ν [mm/s], from a smoothed run.

    The twin's own evaluation (:meth:`ajtwin.estimation.TwinRun.line_at`: the smoothed
    states and their total covariance through the output model and the speed law with its
    uncertainty), as the part map's arrays: mean (n, 2) and σ (n, 2) of [L_w, L_o] in µm.
    ``progress(done)`` after each block of points.
    """
    line = run.line_at(times_s, speeds_mm_s, smoothed=True, progress=progress)
    mean = np.stack([line.linewidth_um, line.overspray_um], axis=1)
    sd = np.stack([line.linewidth_std_um, line.overspray_std_um], axis=1)
    return mean, sd


# --------------------------------------------------------------------------- #
# Portions and their sample points
# --------------------------------------------------------------------------- #


def sample_points(job, portions: pd.DataFrame, step_mm: float = STEP_MM) -> pd.DataFrame:
    """Points along every portion, at most ``step_mm`` apart, both ends included.

    Returns one row per point: ``portion`` (row of ``portions``), ``s_mm`` (arclength along
    the stroke), ``x_mm``, ``y_mm``, ``time_s`` (when the nozzle printed it), ``speed_mm_s``
    (the platen speed there) and ``weight_mm`` (the length the point stands for: the
    trapezoid rule along the portion; 0 for a portion of zero length).
    """
    if not (step_mm > 0 and math.isfinite(step_mm)):
        raise ValueError(f"step_mm must be a positive length, got {step_mm}")
    length = portions["length_mm"].to_numpy(dtype=float)
    count = np.maximum(2, np.ceil(length / step_mm - 1e-9).astype(np.int64) + 1)
    index = np.repeat(np.arange(len(portions)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    j = np.arange(index.size) - first
    last = count[index] - 1
    frac = j / last
    s_from = portions["s_from_mm"].to_numpy(dtype=float)[index]
    s = s_from + frac * length[index]
    stroke = portions["stroke"].to_numpy(dtype=np.int64)[index]
    points = job.point_at(stroke, s)
    spacing = length[index] / last
    weight = np.where((j == 0) | (j == last), 0.5, 1.0) * spacing
    speed = np.asarray(job.segments["speed_mm_s"], dtype=float)[points.segment]
    return pd.DataFrame(
        {
            "portion": index,
            "s_mm": s,
            "x_mm": points.x_mm,
            "y_mm": points.y_mm,
            "time_s": points.time_s,
            "speed_mm_s": speed,
            "weight_mm": weight,
        }
    )


def _per_portion(values: np.ndarray, index: np.ndarray, n: int, how: str) -> np.ndarray:
    """Reduce point values to their portions (``index`` sorted): min, max or sum."""
    starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
    out = np.full(n, np.nan)
    reduce = {"min": np.minimum, "max": np.maximum, "sum": np.add}[how]
    out[index[starts]] = reduce.reduceat(values, starts)
    return out


def portion_table(
    portions: pd.DataFrame,
    points: pd.DataFrame,
    tolerance: Tolerance | None,
    flag_probability: float = FLAG_PROBABILITY,
) -> pd.DataFrame:
    """The strokes.csv table from the portions and their evaluated points.

    ``points`` carries ``lw_mean_um``, ``lw_sd_um``, ``lo_mean_um``, ``lo_sd_um`` per point
    (:func:`line_at`). Means are length-weighted over the portion; lo/hi are the band's
    envelope over it (lowest μ − 2σ, highest μ + 2σ); ``p_out`` the worst point's
    probability (module docstring); NaN without a tolerance.
    """
    n = len(portions)
    idx = points["portion"].to_numpy(dtype=np.int64)
    weight = points["weight_mm"].to_numpy(dtype=float)
    total = _per_portion(weight, idx, n, "sum")
    out = {}

    def weighted(column):
        value = points[column].to_numpy(dtype=float)
        summed = _per_portion(value * weight, idx, n, "sum")
        plain = _per_portion(value, idx, n, "sum") / np.bincount(idx, minlength=n)
        return np.where(total > 0, summed / np.where(total > 0, total, 1.0), plain)

    for name in ("lw", "lo"):
        mean = points[f"{name}_mean_um"].to_numpy(dtype=float)
        sd = points[f"{name}_sd_um"].to_numpy(dtype=float)
        out[f"{name}_mean_um"] = weighted(f"{name}_mean_um")
        out[f"{name}_lo_um"] = _per_portion(mean - 2 * sd, idx, n, "min")
        out[f"{name}_hi_um"] = _per_portion(mean + 2 * sd, idx, n, "max")
        out[f"{name}_sd_um"] = weighted(f"{name}_sd_um")
    speed = _per_portion(points["speed_mm_s"].to_numpy(dtype=float) * weight, idx, n, "sum")
    if tolerance is None:
        p_out = np.full(n, np.nan)
    else:
        p_point = out_of_tolerance_probability(
            points["lw_mean_um"].to_numpy(dtype=float),
            points["lw_sd_um"].to_numpy(dtype=float),
            tolerance,
        )
        p_out = _per_portion(p_point, idx, n, "max")
    table = pd.DataFrame(
        {
            "feature": portions["feature"].to_numpy(),
            "stroke": portions["stroke"].to_numpy(),
            "portion": portions["portion"].to_numpy(),
            "repetition": portions["repetition"].to_numpy(),
            "base_stroke": portions["base_stroke"].to_numpy(),
            "from_x_mm": portions["x_from_mm"].to_numpy(),
            "from_y_mm": portions["y_from_mm"].to_numpy(),
            "to_x_mm": portions["x_to_mm"].to_numpy(),
            "to_y_mm": portions["y_to_mm"].to_numpy(),
            "length_mm": portions["length_mm"].to_numpy(),
            "printed_from_s": portions["t_from_s"].to_numpy(),
            "printed_to_s": portions["t_to_s"].to_numpy(),
            "speed_mm_s": np.where(total > 0, speed / np.where(total > 0, total, 1.0), 0.0),
            **out,
            "p_out": p_out,
            "flagged": np.nan_to_num(p_out, nan=0.0) >= flag_probability,
        }
    )
    return table[list(PORTION_COLUMNS)]


# --------------------------------------------------------------------------- #
# Alarms on the part
# --------------------------------------------------------------------------- #

ALARM_COLUMNS = (
    "alarm",
    "cause",
    "description",
    "detectors",
    "detected_s",
    "onset_s",
    "detected_x_mm",
    "detected_y_mm",
    "detected_stroke",
    "detected_repetition",
    "onset_x_mm",
    "onset_y_mm",
    "onset_stroke",
    "onset_repetition",
)


def place_alarms(job, events) -> pd.DataFrame:
    """Each alarm on the part: where the nozzle was when it was raised and at its onset.

    ``events``: anomaly events (objects or dicts with ``detected_s``, ``onset_s``,
    ``cause``, ``description``, ``detectors``). Positions from :meth:`Job.state_at`; the
    stroke is −1 when the shutter was closed at that moment; the repetition is the run of
    a looped job the nozzle was in.
    """
    rows = []
    for number, ev in enumerate(events, start=1):
        get = ev.get if isinstance(ev, dict) else lambda key, e=ev: getattr(e, key)
        detectors = get("detectors")
        rows.append(
            {
                "alarm": number,
                "cause": str(get("cause")),
                "description": str(get("description")),
                "detectors": detectors
                if isinstance(detectors, str)
                else ", ".join(str(d) for d in detectors or ()),
                "detected_s": float(get("detected_s")),
                "onset_s": float(get("onset_s")),
            }
        )
    table = pd.DataFrame(rows, columns=["alarm", "cause", "description", "detectors",
                                        "detected_s", "onset_s"])  # fmt: skip
    for when in ("detected", "onset"):
        state = job.state_at(table[f"{when}_s"].to_numpy(dtype=float))
        table[f"{when}_x_mm"] = state.x_mm
        table[f"{when}_y_mm"] = state.y_mm
        table[f"{when}_stroke"] = state.stroke
        offsets = np.asarray(job.repetition_offsets_s, dtype=float)
        run = np.searchsorted(offsets, table[f"{when}_s"].to_numpy(dtype=float), side="right")
        table[f"{when}_repetition"] = np.clip(run - 1, 0, len(offsets) - 1)
    return table[list(ALARM_COLUMNS)]


def alarm_of(printed_to_s, alarms: pd.DataFrame) -> np.ndarray:
    """The alarm each portion was printed under: the latest whose estimated onset came
    before the portion's end (0: printed before any alarm's onset)."""
    end = np.asarray(printed_to_s, dtype=float)
    if alarms is None or len(alarms) == 0:
        return np.zeros(end.shape, dtype=np.int64)
    order = np.argsort(alarms["onset_s"].to_numpy(dtype=float), kind="stable")
    onset = alarms["onset_s"].to_numpy(dtype=float)[order]
    number = alarms["alarm"].to_numpy(dtype=np.int64)[order]
    k = np.searchsorted(onset, end, side="right") - 1
    return np.where(k >= 0, number[np.maximum(k, 0)], 0)


def line_drivers(run, times_s, speeds_mm_s, reference_s: float) -> pd.DataFrame:
    """What moved the line at print times τ, read from the twin's smoothed run.

    For each state i (and the inputs as one), L_w(τ) is evaluated again with x_i (or u) held
    at its value at ``reference_s`` (u: its median over the :data:`INPUT_REFERENCE_S` seconds
    from there); the change that state made is
    ΔL_w,i = L_w(x(τ)) − L_w(x(τ) with x_i(reference)). The driver is the one with the
    largest |ΔL_w,i|.

    Returns one row per τ: ``driver`` (a state name of :data:`STATE_NAMES` or
    :data:`INPUTS_DRIVER`), ``driver_from``, ``driver_to`` (the state at the reference and at
    τ, display units; NaN for the inputs), ``driver_lw_um`` (ΔL_w of the driver), and
    ΔL_w,i of every candidate (``lw_change_<name>``; kept with the map, not in strokes.csv).
    """
    times = np.asarray(times_s, dtype=float)
    speeds = np.asarray(speeds_mm_s, dtype=float)
    src = run.smoothed if run.smoothed is not None else run.filtered
    means = np.asarray(src.means, dtype=float)
    covariances = run.total_covariances(run.smoothed is not None)
    inputs = np.asarray(run.inputs, dtype=float)
    step_t = np.asarray(run.time_s, dtype=float)

    def width(x, u):
        args = (run.line_model, step_t, x, covariances, u, times, speeds)
        return np.asarray(line_from_states(*args).linewidth_um)

    k, w, held = interpolation(step_t, [reference_s])
    x_ref = means[k[0]] + w[0] * (means[min(k[0] + 1, len(means) - 1)] - means[k[0]])
    now = width(means, inputs)
    changes = []
    for i in range(len(STATE_NAMES)):
        held_state = means.copy()
        held_state[:, i] = x_ref[i]
        changes.append(now - width(held_state, inputs))
    # the inputs as set at the reference: their median over the minute from it (one logged
    # second carries its sensors' noise, which is no change of the settings)
    first = int(held[0])
    set_then = np.nanmedian(inputs[first : first + INPUT_REFERENCE_S], axis=0)
    changes.append(now - width(means, np.broadcast_to(set_then, inputs.shape)))
    changes = np.stack(changes, axis=1)
    best = np.argmax(np.abs(changes), axis=1)
    names = np.array([*STATE_NAMES, INPUTS_DRIVER])[best]
    tk, tw, _ = interpolation(step_t, times)
    x_now = means[tk] + tw[:, None] * (means[np.minimum(tk + 1, len(means) - 1)] - means[tk])
    scale = np.array([units.display(n).scale for n in STATE_NAMES])
    is_state = best < len(STATE_NAMES)
    column = np.minimum(best, len(STATE_NAMES) - 1)
    rows = np.arange(len(times))
    return pd.DataFrame(
        {
            "driver": names,
            "driver_from": np.where(is_state, (x_ref * scale)[column], np.nan),
            "driver_to": np.where(is_state, x_now[rows, column] * scale[column], np.nan),
            "driver_lw_um": changes[rows, best],
            **{
                f"{CHANGE_PREFIX}{name}": changes[:, k]
                for k, name in enumerate((*STATE_NAMES, INPUTS_DRIVER))
            },
        }
    )


def explain_flagged(table: pd.DataFrame, alarms: pd.DataFrame, run) -> pd.DataFrame:
    """``table`` with :data:`CAUSE_COLUMNS`: for each flagged portion the alarm it was
    printed under and its cause (``'no alarm'`` when none), and what the twin reads as
    having moved its line (:func:`line_drivers`, against the first trace printed, at the
    portion's middle). ``run``: the smoothed run (None: no driver)."""
    out = table.copy()
    flagged = out["flagged"].to_numpy(dtype=bool)
    out["alarm"] = np.where(flagged, alarm_of(out["printed_to_s"], alarms), 0)
    causes = dict(zip(alarms["alarm"], alarms["cause"])) if len(alarms) else {}
    out["cause"] = [
        (causes.get(a, "") if a else "no alarm") if f else "" for a, f in zip(out["alarm"], flagged)
    ]
    out["driver"] = ""
    candidates = [f"{CHANGE_PREFIX}{name}" for name in (*STATE_NAMES, INPUTS_DRIVER)]
    for column in ("driver_from", "driver_to", "driver_lw_um", *candidates):
        out[column] = np.nan
    if flagged.any() and run is not None and getattr(run, "line_model", None) is not None:
        rows = out.index[flagged]
        middle = 0.5 * (out.loc[rows, "printed_from_s"] + out.loc[rows, "printed_to_s"])
        first = float(out["printed_from_s"].min())
        drivers = line_drivers(run, middle, out.loc[rows, "speed_mm_s"], first)
        for column in drivers.columns:
            out.loc[rows, column] = drivers[column].to_numpy()
    return out


def cause_groups(part) -> list[dict]:
    """The flagged portions grouped by cause, each group as a person reads it.

    One dict per alarm the flagged portions were printed under, and one for those printed
    under none: ``alarm`` (0: none), ``cause``, ``sentence`` (the cause in words, since when,
    and the action; for none, that no alarm was raised), ``driver`` (what the twin reads as
    having moved the line, in words), ``portions``, ``length_mm``, ``from_min``, ``to_min``
    (print time of the group's first and last portion, minutes past the print's start).
    """
    table = part.portions
    if "alarm" not in table.columns:
        return []
    flagged = table[table["flagged"].to_numpy(dtype=bool)]
    groups = []
    for alarm, group in flagged.groupby("alarm", sort=True):
        alarm = int(alarm)
        if alarm:
            row = part.alarms.loc[part.alarms["alarm"] == alarm].iloc[0]
            sentence = f"A{alarm} " + alarm_sentence(row["cause"], row["onset_s"], part.machine)
            cause = str(row["cause"])
        else:
            sentence = "no alarm was raised while these were printed"
            cause = "no alarm"
        groups.append(
            {
                "alarm": alarm,
                "cause": cause,
                "sentence": sentence,
                "driver": driver_text(group),
                "portions": int(len(group)),
                "length_mm": float(group["length_mm"].sum()),
                "from_min": units.print_minutes(float(group["printed_from_s"].min())),
                "to_min": units.print_minutes(float(group["printed_to_s"].max())),
            }
        )
    return groups


def driver_text(group: pd.DataFrame) -> str:
    """What moved the line of a group of flagged portions, in words: the driver of most of
    them, its change since the first trace and the L_w change it made (median), and the
    next candidate when it made at least a quarter as much."""
    named = group[group["driver"].astype(str) != ""]
    if named.empty:
        return "the twin's states were not kept with this map (no driver)"
    driver = named["driver"].mode().iloc[0]
    rows = named[named["driver"] == driver]
    effect = float(np.median(rows["driver_lw_um"]))
    share = f"{len(rows)} of {len(group)}" if len(rows) < len(group) else "all"
    change = f"L_w {effect:+.1f} µm"
    if driver == INPUTS_DRIVER:
        text = f"the twin reads the input settings' change ({change})"
    else:
        unit = units.display(driver)
        then = units.readable(float(np.median(rows["driver_from"])))
        later = units.readable(float(np.median(rows["driver_to"])))
        text = (
            f"the twin reads {unit.words} {unit.symbol} {then} → {later} {unit.unit} since the "
            f"first trace ({change})"
        )
    others = {
        name: float(np.median(named[f"{CHANGE_PREFIX}{name}"]))
        for name in (*STATE_NAMES, INPUTS_DRIVER)
        if name != driver and f"{CHANGE_PREFIX}{name}" in named.columns
    }
    if others:
        name, other = max(others.items(), key=lambda item: abs(item[1]))
        if abs(other) >= 0.25 * abs(effect) and abs(other) >= 0.05:
            what = "the input settings" if name == INPUTS_DRIVER else units.display(name).symbol
            text += f", then {what} (L_w {other:+.1f} µm)"
    return f"{text} for {share} portions"


# --------------------------------------------------------------------------- #
# The map
# --------------------------------------------------------------------------- #


@dataclass
class PartMap:
    """The part quality map of one print (see the module docstring).

    Attributes
    ----------
    job : ajtwin.job.Job
        The job as printed (looped as the print ran it).
    portions : DataFrame
        One row per stroke portion printed within the record (:data:`PORTION_COLUMNS`).
    points : DataFrame
        The sample points (:func:`sample_points`) with the line's mean and σ at each.
    alarms : DataFrame
        The alarms on the part (:func:`place_alarms`).
    tolerance : Tolerance or None
    flag_probability : float
    source : str
        What print this is (file, or machine and print number).
    notes : list of str
        What the reader should know (portions not printed within the record, …).
    """

    job: object
    portions: pd.DataFrame
    points: pd.DataFrame
    alarms: pd.DataFrame
    tolerance: Tolerance | None
    flag_probability: float = FLAG_PROBABILITY
    source: str = ""
    notes: list = field(default_factory=list)
    #: the smoothed run (TwinRun) the map was made from (None when built from elsewhere)
    run: object = None
    #: the speed law's exponents the line was drawn with (SpeedExponents; None: not known)
    speed_exponents: object = None
    #: the registered machine the print ran on (named in the actions), None if unknown
    machine: str | None = None

    @property
    def program(self) -> str:
        """The program's file name."""
        return str(self.job.path).replace("\\", "/").rsplit("/", 1)[-1]

    def flagged(self) -> pd.DataFrame:
        """The flagged portions, most probably out first."""
        table = self.portions[self.portions["flagged"]]
        return table.sort_values(["p_out", "printed_from_s"], ascending=[False, True])

    def feature_summary(self) -> pd.DataFrame:
        """Per feature: strokes, portions, printed and flagged length, L_w range, worst P."""
        table = self.portions.assign(
            flagged_mm=np.where(self.portions["flagged"], self.portions["length_mm"], 0.0),
            weighted=self.portions["lw_mean_um"] * self.portions["length_mm"],
        )
        grouped = table.groupby("feature", sort=True)
        summary = pd.DataFrame(
            {
                "strokes": grouped["stroke"].nunique(),
                "portions": grouped.size(),
                "printed_mm": grouped["length_mm"].sum(),
                "flagged_portions": grouped["flagged"].sum(),
                "flagged_mm": grouped["flagged_mm"].sum(),
                "lw_mean_um": grouped["weighted"].sum() / grouped["length_mm"].sum(),
                "lw_min_um": grouped["lw_mean_um"].min(),
                "lw_max_um": grouped["lw_mean_um"].max(),
                "p_out_max": grouped["p_out"].max(),
            }
        ).reset_index()
        summary.insert(1, "name", [self.feature_label(f) for f in summary["feature"]])
        return summary

    def feature_label(self, feature) -> str:
        """A feature as a person reads it: its name from the program, ``feature N`` when it
        has none, ``not in a named feature`` for strokes outside every ``!Feature``."""
        feature = int(feature)
        if feature < 0:
            return "not in a named feature"
        return self.job.feature_names.get(feature, "") or f"feature {feature}"

    @property
    def has_features(self) -> bool:
        """The program names features (``!Feature`` comments) the strokes belong to."""
        return bool((self.portions["feature"].to_numpy() >= 0).any())

    def coverage_of(self, true_linewidth_um) -> float:
        """Share of the printed length whose true width (one value per point) lies in the
        ±2σ band."""
        mean = self.points["lw_mean_um"].to_numpy(dtype=float)
        sd = self.points["lw_sd_um"].to_numpy(dtype=float)
        truth = np.asarray(true_linewidth_um, dtype=float)
        inside = np.abs(truth - mean) <= 2.0 * sd
        weight = self.points["weight_mm"].to_numpy(dtype=float)
        ok = np.isfinite(truth)
        return float(np.sum(weight[ok] * inside[ok]) / np.sum(weight[ok]))


def evaluate_portions(
    job,
    line,
    tolerance: Tolerance | None,
    *,
    printed_until_s: float,
    map_settings: MapSettings = MAP_DEFAULTS,
    progress=None,
):
    """(portions table, points, notes) of the strokes printed by ``printed_until_s``, cut,
    sampled and judged as ``map_settings`` says.

    ``line(times_s, speeds_mm_s, progress) -> (mean (n, 2), sd (n, 2))`` evaluates the
    line at every sample point (:func:`line_at` with a run bound), calling ``progress(done)``
    as it goes (None: no progress); ``progress(done, total)`` is called alike. Portions not
    finished by ``printed_until_s`` are left out (a note says how many).
    """
    portion_mm, step_mm, flag_probability = map_settings
    if not 0.0 <= flag_probability <= 1.0:
        raise ValueError(f"flag_probability must lie in [0, 1], got {flag_probability}")
    portions = job.portions(portion_mm)
    done = portions["t_to_s"].to_numpy(dtype=float) <= printed_until_s + 1e-9
    notes = []
    if not done.all():
        left = int((~done).sum())
        notes.append(
            f"{left} of {len(portions)} portions were printed after the record ends "
            f"({printed_until_s:g} s) and are left out"
        )
    portions = portions[done].reset_index(drop=True)
    points = sample_points(job, portions, step_mm)
    times, speeds = points["time_s"].to_numpy(), points["speed_mm_s"].to_numpy()
    total = len(times)
    mean, sd = line(times, speeds, None if progress is None else lambda done: progress(done, total))
    points["lw_mean_um"], points["lo_mean_um"] = mean[:, 0], mean[:, 1]
    points["lw_sd_um"], points["lo_sd_um"] = sd[:, 0], sd[:, 1]
    table = portion_table(portions, points, tolerance, flag_probability)
    return table, points, notes


def build_part_map(
    job,
    run,
    tolerance: Tolerance | None,
    *,
    events=(),
    source: str = "",
    map_settings: MapSettings = MAP_DEFAULTS,
    progress=None,
) -> PartMap:
    """The part map of a smoothed run (:class:`~ajtwin.estimation.twin.TwinRun`) over a
    print of ``job`` (module docstring), cut, sampled and judged as ``map_settings`` says.

    ``events``: the print's alarms (placed on the part). ``progress(done, total)`` is
    called as the sample points are evaluated.
    """
    end_s = float(np.asarray(run.time_s)[-1]) + 1.0

    def line(times, speeds, step):
        return line_at(run, times, speeds, step)

    table, points, notes = evaluate_portions(
        job,
        line,
        tolerance,
        printed_until_s=end_s,
        map_settings=map_settings,
        progress=progress,
    )
    alarms = place_alarms(job, events)
    return PartMap(
        job,
        explain_flagged(table, alarms, run),
        points,
        alarms,
        tolerance,
        map_settings.flag_probability,
        source,
        notes,
    )


def part_map_of_record(
    record,
    job,
    tolerance: Tolerance | None,
    *,
    twin: Twin | None = None,
    start=None,
    source: str = "",
    map_settings: MapSettings = MAP_DEFAULTS,
    events=None,
    twin_progress=None,
    line_progress=None,
    learn_speed: bool = True,
) -> PartMap:
    """Run the twin (smoothed) over ``record`` as the print ran ``job`` and map its part.

    ``learn_speed``: first learn the speed law's exponents from the camera's readings of
    this print (:func:`~ajtwin.estimation.line_speed_fit.teach_speed_law`; the twin's
    belief is the prior).

    ``job``: the job as printed (:func:`ajtwin.estimation.print_time.job_as_printed`); on a
    job record the twin files the camera's frames at their print times with it
    (:func:`smoothed_run`). ``twin``/``start``: the machine's twin and where its print
    starts (default: the initial fit of a new twin). ``events``: the print's alarms;
    default: those the detectors raise over this run
    (:func:`ajtwin.apps.detection.batch.detect_run`). ``map_settings``: how the part is
    cut, sampled and judged.
    """
    twin = twin or Twin.default()
    if learn_speed and job is not None and is_job_record(record):
        teach_speed_law(twin, record, job)
    run = smoothed_run(record, twin, start, twin_progress, job=job)
    if events is None:
        events = detect_run(run, record).events
    part = build_part_map(
        job,
        run,
        tolerance,
        events=events,
        source=source,
        map_settings=map_settings,
        progress=line_progress,
    )
    part.run = run
    part.speed_exponents = twin.speed_exponents
    return part
