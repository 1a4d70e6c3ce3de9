"""A job print's columns for samples whose link carries none (model reference §12).

The OPC UA ``SampleBuffer`` gives a second's time, inputs and outputs, not the job's columns
(``shutter_open``, ``platen_speed_mm_s``, ``printed_at_s``). A controller or twin that knows
the program the machine runs and where its camera looks fills them in: the shutter and the
platen speed from the program's timeline at the sample's print time
(:meth:`ajtwin.job.Job.state_at`), and, for a sample with a camera measurement, the print
time τ of the trace under the camera (the geometry of model reference §12: the trace
printed last before t within the view's field around p(t) + offset, :meth:`ajtwin.job.Job.
locate`) — what the virtual printer's camera measured and what a real camera's software
knows from the stage position. A machine runs its program from its start when the print
starts (t = 0) and again from its start when it ends, over the same part.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),40,0\\nOUT0.0=0",
...                         process_speed_mm_s=2.0)
>>> columns = JobColumns(job, "trailing", (-5.0, 0.0))
>>> y = np.array([[np.nan] * 5, [50.0, 30.0, 5600.0, 5600.0, 1e-9]])
>>> out = columns.fill(np.array([1.0, 8.0]), y)          # at 8 s the camera sees x = 11 mm
>>> out["shutter_open"].tolist(), out["platen_speed_mm_s"].tolist()
([1.0, 1.0], [2.0, 2.0])
>>> out["printed_at_s"].round(6).tolist()                 # printed at 5.5 s
[nan, 5.5]
"""

from __future__ import annotations

import math

import numpy as np

from ajtwin.estimation.print_time import load_print_time_settings
from ajtwin.io.schema import MAX_RECORD_SECONDS
from ajtwin.job import loop_job

#: A live job print is looped to this length [s] (the program again over the same part when
#: it ends): the longest print a record may span. The loop is answered run by run
#: (:class:`ajtwin.job.LoopedJob`), so its length costs nothing until it is reached.
LIVE_LOOP_S = float(MAX_RECORD_SECONDS)


def live_loop(job, duration_s: float = LIVE_LOOP_S):
    """The program run again and again over the same part to ``duration_s``
    (:func:`ajtwin.job.loop_job`; the job as it is when it is looped already or lasts that
    long)."""
    if job.repetitions > 1 or job.duration_s >= duration_s:
        return job
    return loop_job(job, float(duration_s))


class JobColumns:
    """Fills a job print's columns of 1 Hz samples from the program and the camera.

    Parameters
    ----------
    job : ajtwin.job.Job or ajtwin.job.LoopedJob
        The job as the machine runs it (looped: :func:`live_loop`).
    camera_mode : {"trailing", "at_nozzle", "inspection"}
    offset_mm : (float, float)
        The trailing camera's view centre relative to the nozzle [mm].
    field_radius_mm : float, optional
        A trace is seen this close to the view centre (default ``data/print_time.toml``).
    """

    def __init__(self, job, camera_mode: str, offset_mm=(0.0, 0.0), field_radius_mm=None):
        self.job = job
        self.camera_mode = camera_mode
        self.offset_mm = tuple(float(v) for v in offset_mm)
        radius = load_print_time_settings()["field_radius_mm"]
        self.field_radius_mm = float(radius if field_radius_mm is None else field_radius_mm)
        if not (math.isfinite(self.field_radius_mm) and self.field_radius_mm > 0):
            raise ValueError(f"field_radius_mm = {field_radius_mm!r} must be a positive length")

    def fill(self, time_s, outputs) -> dict:
        """The columns of samples at ``time_s`` (n,) with ``outputs`` (n, 5).

        Returns
        -------
        dict of ndarray
            ``shutter_open`` (n,) (0/1), ``platen_speed_mm_s`` (n,), ``printed_at_s`` (n,)
            (NaN for a row without a camera measurement) and ``outputs`` (n, 5): as given,
            but a camera measurement the geometry cannot place (no trace in the view of a
            trailing camera, or an inspection pass's, which this link cannot follow) is
            removed rather than filed at the row's own time.
        """
        t = np.asarray(time_s, dtype=float).reshape(-1)
        y = np.asarray(outputs, dtype=float).reshape(-1, 5)
        state = self.job.state_at(t)
        measured = np.isfinite(y[:, 0]) | np.isfinite(y[:, 1])
        printed_at = np.full(t.size, np.nan)
        y = y.copy()
        if self.camera_mode == "at_nozzle":
            printed_at = np.where(measured, t, np.nan)
        elif self.camera_mode == "trailing" and measured.any():
            dx, dy = self.offset_mm
            hits = self.job.locate(
                state.x_mm[measured] + dx,
                state.y_mm[measured] + dy,
                self.field_radius_mm,
                before_s=t[measured],
            )
            printed_at[measured] = np.where(hits.found, hits.print_time_s, np.nan)
        y[measured & ~np.isfinite(printed_at), :2] = np.nan
        return {
            "shutter_open": state.shutter_open.astype(float),
            "platen_speed_mm_s": np.asarray(state.speed_mm_s, dtype=float),
            "printed_at_s": printed_at,
            "outputs": y,
        }
