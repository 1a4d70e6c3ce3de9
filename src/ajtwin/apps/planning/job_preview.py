"""The job's seconds ahead, as the MPC weighs them (model reference §12).

A controller that knows the program knows, for every second ahead, whether a line will be
printed and at what speed. :class:`JobPreview` turns the job's timeline into what the MPC's
cost needs per second k of its horizon (:func:`ajtwin.apps.planning.mpc.plan_cost`):

* ℓ_k — the length printed in second k relative to a second printed at ν_ref (0 while the
  shutter is closed or the stage stands still: a width error there costs nothing, so the
  optimiser may move the inputs then; 2 for a second at 2 ν_ref: the cost is per printed
  length, as the comparison's figures are);
* f_w,k, f_o,k — the speed law's factors at the speed printed in second k
  (:mod:`ajtwin.model.line_speed`): the line printed then is the model's line at ν_ref
  times f. A planned speed change is thus met with input moves (feed-forward through the
  model) before the line would move.

Without a job every second is a second of straight line at ν_ref: ℓ = f = 1.

Examples
--------
>>> from ajtwin.job import read_program_text
>>> job = read_program_text("ptp/e (X,Y),0,0\\nOUT0.0=1\\nptp/e (X,Y),8,0\\nOUT0.0=0",
...                         process_speed_mm_s=4.0)
>>> preview = JobPreview(job, horizon_s=4)
>>> preview.line(0.0).round(4).tolist()        # 2 s at 4 mm/s, then nothing printed
[[2.0, 0.8123, 0.8123], [2.0, 0.8123, 0.8123], [0.0, 1.0, 1.0], [0.0, 1.0, 1.0]]
"""

from __future__ import annotations

import math

import numpy as np

from ajtwin.model.line_speed import LineSpeedLaw, line_speed_factors, load_line_speed_law


class JobPreview:
    """Per second of a job: printed length relative to ν_ref and the speed law's factors.

    Parameters
    ----------
    job : ajtwin.job.Job
        The job as the machine prints it (looped to the print's length).
    horizon_s : int
        The MPC's horizon H [s]: :meth:`line` returns H rows.
    speed_law : LineSpeedLaw, optional
        The twin's speed law (default ``data/line_speed.toml``).

    Attributes
    ----------
    length : ndarray (T,)
        ℓ_k for the seconds k = 0 … T − 1 of the job (and H seconds after its end, 0).
    factors : ndarray (T, 2)
        f_w, f_o of the line printed in each second (1 where nothing is).
    """

    def __init__(self, job, horizon_s: int, speed_law: LineSpeedLaw | None = None):
        self.horizon_s = int(horizon_s)
        if self.horizon_s < 1:
            raise ValueError(f"horizon_s = {horizon_s!r} must be ≥ 1")
        law = speed_law or load_line_speed_law()
        n = int(math.ceil(job.duration_s - 1e-9)) + self.horizon_s
        table = job.per_second(duration_s=n)
        length = np.nan_to_num(table["printed_length_mm"].to_numpy(dtype=float))
        speed = table["printing_speed_mm_s"].to_numpy(dtype=float)
        printing = length > 0
        nu = np.where(printing & np.isfinite(speed), speed, law.reference_speed_mm_s)
        f_w, f_o = line_speed_factors(nu, law)
        self.length = length / law.reference_speed_mm_s
        self.factors = np.stack([np.asarray(f_w), np.asarray(f_o)], axis=1)
        self.factors[~printing] = 1.0

    def line(self, time_s: float) -> np.ndarray:
        """(H, 3): ℓ, f_w, f_o of the seconds time_s, time_s + 1, … (the MPC's ``line``).

        Seconds past the end of the job print nothing (ℓ = 0).
        """
        k0 = int(round(float(time_s)))
        out = np.zeros((self.horizon_s, 3))
        out[:, 1:] = 1.0
        lo, hi = max(k0, 0), min(k0 + self.horizon_s, self.length.size)
        if hi > lo:
            out[lo - k0 : hi - k0, 0] = self.length[lo:hi]
            out[lo - k0 : hi - k0, 1:] = self.factors[lo:hi]
        return out


def straight_line(horizon_s: int) -> np.ndarray:
    """(H, 3) of ones: a straight line printed at ν_ref every second (no job)."""
    return np.ones((int(horizon_s), 3))
