"""Detection: the anomaly detectors on the twin's innovations and the model–machine guard.

* :mod:`~ajtwin.apps.detection.settings` — thresholds (``data/detectors.toml``).
* :mod:`~ajtwin.apps.detection.statistics` — NIS, windowed NIS, CUSUM, long-run scale.
* :mod:`~ajtwin.apps.detection.causes` — the likely cause of an event.
* :mod:`~ajtwin.apps.detection.streaming` — the detector, one step at a time.
* :mod:`~ajtwin.apps.detection.batch` — the detector over a finished print.
* :mod:`~ajtwin.apps.detection.mismatch` — the model–machine mismatch guard.
"""
