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

#: seconds of the job worked out at once (a block kept, the next made when asked)
_BLOCK_S = 3600


class JobPreview:
    """Per second of a job: printed length relative to ν_ref and the speed law's factors.

    The seconds are worked out a block of an hour at a time, as :meth:`line` reaches them,
    so a job looped over days (:class:`ajtwin.job.LoopedJob`) costs no more than an hour's.

    Parameters
    ----------
    job : ajtwin.job.Job or ajtwin.job.LoopedJob
        The job as the machine prints it (looped to the print's length).
    horizon_s : int
        The MPC's horizon H [s]: :meth:`line` returns H rows.
    speed_law : LineSpeedLaw, optional
        The twin's speed law (default ``data/line_speed.toml``).
    """

    def __init__(self, job, horizon_s: int, speed_law: LineSpeedLaw | None = None):
        self.horizon_s = int(horizon_s)
        if self.horizon_s < 1:
            raise ValueError(f"horizon_s = {horizon_s!r} must be ≥ 1")
        self.job = job
        self.law = speed_law or load_line_speed_law()
        #: seconds of the job (those after print nothing)
        self.n_seconds = int(math.ceil(job.duration_s - 1e-9))
        self._blocks: dict[int, np.ndarray] = {}

    def _block(self, b: int) -> np.ndarray:
        """(_BLOCK_S, 3): ℓ, f_w, f_o of the seconds b·_BLOCK_S … (kept: this block and the
        one before)."""
        if b not in self._blocks:
            law = self.law
            start = b * _BLOCK_S
            table = self.job.per_second(duration_s=_BLOCK_S, start_s=float(start))
            length = np.nan_to_num(table["printed_length_mm"].to_numpy(dtype=float))
            length[max(self.n_seconds - start, 0) :] = 0.0
            speed = table["printing_speed_mm_s"].to_numpy(dtype=float)
            printing = length > 0
            nu = np.where(printing & np.isfinite(speed), speed, law.reference_speed_mm_s)
            f_w, f_o = line_speed_factors(nu, law)
            block = np.stack([length / law.reference_speed_mm_s, f_w, f_o], axis=1)
            block[~printing, 1:] = 1.0
            self._blocks = {k: v for k, v in self._blocks.items() if k == b - 1}
            self._blocks[b] = block
        return self._blocks[b]

    def line(self, time_s: float) -> np.ndarray:
        """(H, 3): ℓ, f_w, f_o of the seconds time_s, time_s + 1, … (the MPC's ``line``).

        Seconds past the end of the job print nothing (ℓ = 0).
        """
        k0 = int(round(float(time_s)))
        out = np.zeros((self.horizon_s, 3))
        out[:, 1:] = 1.0
        k = max(k0, 0)
        while k < min(k0 + self.horizon_s, self.n_seconds):
            b, within = divmod(k, _BLOCK_S)
            take = min(_BLOCK_S - within, k0 + self.horizon_s - k, self.n_seconds - k)
            out[k - k0 : k - k0 + take] = self._block(b)[within : within + take]
            k += take
        return out
