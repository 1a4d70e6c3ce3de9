"""The detectors over a whole print: the streaming detector run over arrays.

:func:`detect_anomalies` runs :class:`~ajtwin.apps.detection.streaming.AnomalyDetector`
over a finished run's arrays, so a live twin and a finished print give the same events;
:func:`detect_run` does it for a :class:`~ajtwin.estimation.twin.TwinRun`.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings
from ajtwin.apps.detection.settling import switched_on_s
from ajtwin.apps.detection.streaming import AnomalyDetector


@dataclass
class DetectionResult:
    """Everything the detectors computed over one print."""

    time_s: np.ndarray
    normalised_innovations: np.ndarray  # (T, 5)
    nis_p: np.ndarray  # (T,) per-step χ² tail
    window_nis_p: np.ndarray  # (T,)
    cusum_pos: np.ndarray  # (T, 6): CUSUM_CHANNELS
    cusum_neg: np.ndarray  # (T, 6)
    events: list  # AnomalyEvent
    settings: DetectorSettings
    # the long-run statistics to carry to the machine's next print (AnomalyDetector)
    long_run_history: dict | None = None


#: The arrays of a twin run the detectors read each step, in the order
#: :func:`detect_anomalies` takes them.
DETECTOR_ARRAYS = (
    "time_s",
    "measurements",
    "predicted_outputs",
    "innovation_variances",
    "nis",
    "n_measured",
    "means",
    "predicted_means",
    "covariances",
)


def detect_anomalies(
    time_s,
    measurements,
    predicted_outputs,
    innovation_variances,
    nis,
    n_measured,
    means,
    predicted_means,
    covariances,
    settings: DetectorSettings | None = None,
    inputs=None,
    long_run_history: dict | None = None,
) -> DetectionResult:
    """Run NIS, windowed-NIS and CUSUM tests and group alarms into labelled events.

    :class:`AnomalyDetector` run over the arrays, step by step.

    Parameters
    ----------
    time_s : (T,) seconds
    measurements : (T, 5) measured outputs (NaN = missing)
    predicted_outputs, innovation_variances, nis, n_measured :
        from the EKF (:class:`ajtwin.estimation.filters.FilterResult`)
    means, predicted_means, covariances : (T, 5), (T, 5), (T, 5, 5)
        filtered states x̂_k, predictions x̂_{k|k−1} and P_k (display units)
    settings : DetectorSettings, optional
    inputs : (T, 3), optional
        [mA, sccm, sccm]: runs the vial observer (see :meth:`AnomalyDetector.update`).
    long_run_history : dict, optional
        The machine's carried long-run statistics (see :class:`AnomalyDetector`).

    Returns
    -------
    DetectionResult (its ``long_run_history``: what to carry to the next print)
    """
    return run_detector(
        AnomalyDetector(settings, long_run_history),
        time_s,
        measurements,
        inputs,
        SimpleNamespace(
            predicted_outputs=predicted_outputs,
            innovation_variances=innovation_variances,
            nis=nis,
            n_measured=n_measured,
            means=means,
            predicted_means=predicted_means,
            covariances=covariances,
        ),
    )


def run_detector(detector: AnomalyDetector, time_s, measurements, inputs, filtered):
    """``detector`` over a whole print: times (T,), measurements (T, 5), inputs (T, 3) or
    None, and the filter's results (``filtered``: :data:`DETECTOR_ARRAYS`' names); the
    :class:`DetectionResult`."""
    t = np.asarray(time_s, dtype=float)
    block = SimpleNamespace(time_s=t, measurements=measurements, inputs=inputs, filtered=filtered)
    rows = detector.update_block(block)
    events = detector.finish()
    n_channels = len(CUSUM_CHANNELS)

    def stack(name, shape):
        return np.array([getattr(r, name) for r in rows]).reshape(shape)

    return DetectionResult(
        t,
        stack("normalised_innovation", (len(t), 5)),
        stack("nis_p", (len(t),)),
        stack("window_nis_p", (len(t),)),
        stack("cusum_pos", (len(t), n_channels)),
        stack("cusum_neg", (len(t), n_channels)),
        events,
        detector.settings,
        detector.long_run_history(),
    )


def detect_run(
    run, record, settings: DetectorSettings | None = None, long_run_history: dict | None = None
) -> DetectionResult:
    """:func:`detect_anomalies` on a :class:`~ajtwin.estimation.twin.TwinRun` and its record.

    The measurements are those the filter used (``run.measurements``: on a job print the
    camera's filed at their print times), else the record's outputs. A record whose
    atomizer was switched on as it began (``atomizer_switched_on_s``) begins with a run-in.
    """
    measured = getattr(run, "measurements", None)
    switched_on = switched_on_s(getattr(record, "meta", None))
    detector = AnomalyDetector(settings, long_run_history, switched_on)
    return run_detector(
        detector,
        run.time_s,
        record.outputs if measured is None else measured,
        record.inputs,
        run.filtered,
    )
