"""The speed law's exponents learnt from the camera's readings of a job print (model reference §12).

The twin's speed law (:mod:`ajtwin.model.line_speed`) scales the line printed at platen
speed ν by (ν_ref/ν)^b (L_w) and (ν_ref/ν)^c (L_o). Its packaged exponents are bracketed
by physics, not fitted (``data/line_speed.toml``): far from ν_ref their uncertainty is the
widest part of a part map's band. But a program that prints at several speeds shows the
camera lines of each: the exponents are in its readings.

Within a short window of print time the line's level hardly moves (the states drift over
minutes), so for readings i of window g

    ln y_i = a_g + b s_i + ε_i,     s_i = ln(ν_ref / ν_i),     ε_i ≈ w_i / y_i

over the readings of lines printed inside the law's validity range (a dwell's dot, or a
speed the law clips, holds the law's edge value: not a contrast of the power law). The
window's own level a_g is a nuisance removed by centring within the window, weighted by the
readings' precision y_i² (the camera's noise is additive in µm):

    b̂ = Σ w_i s̃_i ỹ_i / Σ w_i s̃_i²,    Var b̂ = σ̂² / Σ w_i s̃_i²

with s̃, ỹ the centred values and σ̂² the weighted residual variance (the camera's noise
and whatever the level moved within the windows, from the data; the twin's camera σ when
too few readings are left to estimate it). Readings in a window of one speed carry no
information on b and drop out by themselves. The estimate is combined with the prior
b ~ N(b₀, σ₀²) — the packaged law, or what the machine's earlier prints learnt — into the
posterior by precision weighting:

    σ_b⁻² = σ₀⁻² + (Var b̂)⁻¹,     b = σ_b² (b₀/σ₀² + b̂/Var b̂)

and the same for c from L_o. A print of one speed leaves the prior as it was.

Why not a state of the filter: b is a constant of the machine and its ink, seen only in
contrasts between speeds a few seconds apart; a window's contrast does not depend on the
states, so it is learnt before the twin runs and the twin then runs with it (its camera
frames filed and its band drawn with the learnt law).

Examples
--------
>>> import numpy as np
>>> prior = SpeedExponents(0.3, 0.3, 0.125, 0.125)
>>> t = np.arange(400.0)
>>> nu = np.where(t % 20 < 10, 3.0, 5.0)                 # two speeds, 10 s each
>>> width = 60.0 * (2.0 / nu) ** 0.15                    # a machine with b = 0.15
>>> readings = CameraReadings(t, nu, np.stack([width, width], axis=1))
>>> fit = fit_speed_exponents(readings, prior, measurement_std_um=(1.0, 1.0))
>>> round(fit.linewidth_exponent, 3), fit.linewidth_exponent_std < 0.01
(0.15, True)
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from ajtwin.model.line_speed import LineSpeedLaw, load_line_speed_law, read_line_speed_file

#: fewer degrees of freedom than this and σ̂ comes from the twin's camera σ instead
MIN_RESIDUAL_DOF = 10


class SpeedExponents(NamedTuple):
    """The speed law's exponents and their σ (a belief about b and c).

    Attributes
    ----------
    linewidth_exponent, overspray_exponent : float
        b, c.
    linewidth_exponent_std, overspray_exponent_std : float
        Their σ.
    readings : int
        Camera readings with a speed contrast behind the estimate (cumulative over a
        machine's prints; 0: the prior alone).
    speeds_mm_s : tuple
        The distinct platen speeds the readings were printed at [mm/s].
    """

    linewidth_exponent: float
    overspray_exponent: float
    linewidth_exponent_std: float
    overspray_exponent_std: float
    readings: int = 0
    speeds_mm_s: tuple = ()

    @property
    def std(self) -> np.ndarray:
        """(σ_b, σ_c)."""
        return np.array([self.linewidth_exponent_std, self.overspray_exponent_std])

    def law(self, base: LineSpeedLaw | None = None) -> LineSpeedLaw:
        """The speed law with these exponents (``base``: the packaged law)."""
        base = base or load_line_speed_law()
        return base._replace(
            linewidth_exponent=float(self.linewidth_exponent),
            overspray_exponent=float(self.overspray_exponent),
        )

    def to_dict(self) -> dict:
        """JSON-ready (what the registry keeps with a print)."""
        return {
            **{k: float(getattr(self, k)) for k in self._fields[:4]},
            "readings": int(self.readings),
            "speeds_mm_s": [float(v) for v in self.speeds_mm_s],
        }

    @classmethod
    def from_dict(cls, value: dict) -> SpeedExponents:
        """From :meth:`to_dict`'s form (ValueError naming a missing or bad field)."""
        try:
            numbers = [float(value[k]) for k in cls._fields[:4]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"speed exponents {value!r}: {exc}") from None
        if not (np.isfinite(numbers).all() and numbers[2] > 0 and numbers[3] > 0):
            raise ValueError(f"speed exponents {value!r}: finite values, σ > 0")
        speeds = tuple(float(v) for v in value.get("speeds_mm_s", ()))
        return cls(*numbers, int(value.get("readings", 0)), speeds)

    def describe(self) -> str:
        """One line for a report, ``b = 0.158 ± 0.022, c = … (65 camera readings at 3, 5 mm/s)``."""
        if self.readings == 0:
            where = "the packaged prior: no camera readings at two speeds yet"
        else:
            speeds = ", ".join(f"{v:g}" for v in self.speeds_mm_s)
            where = f"{self.readings} camera readings at {speeds} mm/s"
        return (
            f"b = {self.linewidth_exponent:.3f} ± {self.linewidth_exponent_std:.3f}, "
            f"c = {self.overspray_exponent:.3f} ± {self.overspray_exponent_std:.3f} ({where})"
        )


@functools.cache
def prior_exponents() -> SpeedExponents:
    """The packaged belief: [law]'s exponents, σ a quarter of each bracketed range of
    ``data/line_speed.toml`` (the range as ±2σ)."""
    content = read_line_speed_file()
    law, ranges = content["law"], content["uncertainty"]
    std = [
        (float(ranges[name][1]) - float(ranges[name][0])) / 4.0
        for name in ("linewidth_exponent_range", "overspray_exponent_range")
    ]
    return SpeedExponents(
        float(law["linewidth_exponent"]), float(law["overspray_exponent"]), std[0], std[1]
    )


@functools.cache
def learning_window_s() -> float:
    """The window of print time within which the line's level is taken as constant [s]
    (``data/line_speed.toml`` [learning])."""
    return float(read_line_speed_file()["learning"]["window_s"])


class CameraReadings(NamedTuple):
    """A job print's camera readings at their print times, each (n,) or (n, 2).

    Attributes
    ----------
    time_s : ndarray (n,)
        τ: when the trace read was printed [s].
    speed_mm_s : ndarray (n,)
        ν(τ) from the program [mm/s].
    lines_um : ndarray (n, 2)
        [L_w, L_o] read [µm] (NaN: not read).
    """

    time_s: np.ndarray
    speed_mm_s: np.ndarray
    lines_um: np.ndarray


def _column(record, name: str) -> np.ndarray:
    """A record's column, in memory or held on disk (:class:`~ajtwin.io.records.SpooledRecord`)."""
    if hasattr(record, "data"):
        return record.data[name].to_numpy(dtype=float)
    return np.asarray(record.column(name), dtype=float)


def camera_readings(record, job) -> CameraReadings:
    """The camera readings of a job ``record`` printed with the shutter open by ``job``
    (the program as printed), with the speed the program printed them at."""
    tau = _column(record, "printed_at_s")
    lines = np.stack([_column(record, "linewidth_um"), _column(record, "overspray_um")], axis=1)
    if hasattr(record, "data"):
        row_time = np.asarray(record.time_s, dtype=float)
    else:  # held on disk: a 1 Hz grid from its first row
        row_time = record.time_s[0] + np.arange(len(record), dtype=float)
    tau = np.where(np.isfinite(tau), tau, row_time)
    seen = np.isfinite(lines).any(axis=1)
    tau, lines = tau[seen], lines[seen]
    state = job.state_at(tau)
    printed = np.asarray(state.shutter_open, dtype=bool)
    return CameraReadings(
        tau[printed], np.asarray(state.speed_mm_s, dtype=float)[printed], lines[printed]
    )


def _contrast(s, log_y, weight, group):
    """(Σ w s̃ ỹ, Σ w s̃², Σ w ỹ², readings with a contrast, degrees of freedom of the
    residual) within groups: every reading tells the noise about its window's mean, only
    those of windows with two speeds tell b."""
    _, g = np.unique(group, return_inverse=True)
    n_groups = g.max() + 1
    w_sum = np.bincount(g, weight, n_groups)
    s_mean = np.bincount(g, weight * s, n_groups) / w_sum
    y_mean = np.bincount(g, weight * log_y, n_groups) / w_sum
    sc, yc = s - s_mean[g], log_y - y_mean[g]
    varied = np.bincount(g, np.abs(sc) > 1e-12, n_groups) > 0
    informative = varied[g]
    return (
        float(np.sum(weight * sc * yc)),
        float(np.sum(weight * sc * sc)),
        float(np.sum(weight * yc * yc)),
        int(informative.sum()),
        int(len(s) - n_groups - 1),
    )


def fit_speed_exponents(
    readings: CameraReadings,
    prior: SpeedExponents | None = None,
    *,
    law: LineSpeedLaw | None = None,
    window_s: float | None = None,
    measurement_std_um=(3.0, 3.0),
) -> SpeedExponents:
    """The posterior of (b, c) from a print's camera readings (module docstring).

    Parameters
    ----------
    readings : CameraReadings
    prior : SpeedExponents, optional
        What was believed before (default :func:`prior_exponents`; a machine's: what its
        earlier prints learnt).
    law : LineSpeedLaw, optional
        ν_ref and the validity range (default the packaged law).
    window_s : float, optional
        The window of print time sharing one level (default :func:`learning_window_s`).
    measurement_std_um : (float, float)
        The camera's σ of L_w, L_o [µm]: σ̂ when too few readings are left to estimate it.

    Returns
    -------
    SpeedExponents
        The posterior; the prior unchanged when no window held two speeds.
    """
    prior = prior or prior_exponents()
    law = law or load_line_speed_law()
    window = float(window_s if window_s is not None else learning_window_s())
    if not window > 0:
        raise ValueError(f"window_s = {window_s!r}: a positive number of seconds")
    nu = np.asarray(readings.speed_mm_s, dtype=float)
    # a line printed inside the law's validity range: a dwell's dot or a clipped speed
    # holds the law's edge value and would read as a contrast the law does not have
    valid = (nu >= law.min_speed_mm_s) & (nu <= law.max_speed_mm_s)
    s = np.log(law.reference_speed_mm_s / np.where(valid, nu, law.reference_speed_mm_s))
    lines = np.asarray(readings.lines_um, dtype=float).reshape(-1, 2)
    group = np.floor(np.asarray(readings.time_s, float) / window).astype(np.int64)
    posterior = []
    used_readings, used_speeds = 0, set()
    for i in range(2):
        mean0, std0 = prior[i], prior[2 + i]
        y = lines[:, i]
        ok = np.isfinite(y) & (y > 0) & valid
        if ok.sum() < 2:
            posterior.append((mean0, std0))
            continue
        weight = y[ok] ** 2  # precision of ln y: (y/σ)², σ common
        sxy, sxx, syy, informative, dof = _contrast(s[ok], np.log(y[ok]), weight, group[ok])
        if informative == 0 or sxx <= 0:  # no window held two speeds
            posterior.append((mean0, std0))
            continue
        slope = sxy / sxx
        sigma2 = max(syy - slope * sxy, 0.0) / max(dof, 1)  # σ̂² of ln y × y² = σ² [µm²]
        if dof < MIN_RESIDUAL_DOF or sigma2 == 0.0:  # too few to tell, or noise-free
            sigma2 = float(measurement_std_um[i]) ** 2
        var = sigma2 / sxx
        precision = 1.0 / std0**2 + 1.0 / var
        mean = (mean0 / std0**2 + slope / var) / precision
        posterior.append((mean, precision**-0.5))
        if i == 0:
            used_readings = informative
            used_speeds = set(np.round(np.asarray(readings.speed_mm_s)[ok], 6).tolist())
    speeds = prior.speeds_mm_s
    if used_readings:
        speeds = tuple(sorted(set(speeds) | used_speeds))
    return SpeedExponents(
        float(posterior[0][0]),
        float(posterior[1][0]),
        float(posterior[0][1]),
        float(posterior[1][1]),
        int(prior.readings + used_readings),
        speeds,
    )


def learn_speed_exponents(record, job, prior=None, measurement_std_um=(3.0, 3.0)):
    """:func:`fit_speed_exponents` over a job record's camera readings (program ``job``
    as printed)."""
    return fit_speed_exponents(
        camera_readings(record, job), prior, measurement_std_um=measurement_std_um
    )


def teach_speed_law(twin, record, job) -> SpeedExponents:
    """Teach ``twin`` (:class:`~ajtwin.estimation.twin.Twin`) the exponents of a job
    print's camera readings, from what it believed before (the packaged law, or what the
    machine's earlier prints learnt): its frames are then filed and the line and band drawn
    with them. A program of one speed leaves the belief as it was. Returns the belief now."""
    learnt = learn_speed_exponents(record, job, twin.speed_exponents, twin.measurement_std[:2])
    twin.learn_speed_law(learnt)
    return learnt
