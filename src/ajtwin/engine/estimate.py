"""``ajtwin estimate``'s work: the twin over a record, its states to a CSV.

The table has one row per second: the states ± σ, the predicted outputs, NIS, what the
data saw, the vial observer, the mismatch guard's flag and each state's data share
(:meth:`ajtwin.estimation.twin.TwinRun.to_frame`, then the guard's and the share's
columns). Filtered states are taken from the twin a chunk at a time
(:meth:`~ajtwin.estimation.Twin.run` with a ``sink``): the filter's covariances and
Jacobians of a chunk are dropped once its rows are made, and the rows wait in a temporary
folder beside the output until the guard's verdict and the vial observer (which need the
whole print) give their columns; what stays in memory is the guard's per-second inputs
(18 numbers a second), and the observer runs only once the guard has let them go (the two
are never held together). The smoother (``smooth``) and a plot need
the whole run and hold it.

Example
-------
>>> from ajtwin.estimation import Twin
>>> from ajtwin.simulation import simulate
>>> done = estimate_to_csv(Twin.default(), simulate("exp1", seed=1, duration_min=2), "s.csv")
>>> done.rows, done.mismatch.message
(120, 'the model fits this machine')
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.apps.detection.mismatch import (
    GuardInputs,
    assess_run,
    data_share,
    determined_states,
    load_guard_settings,
    settled_level_s,
    without_run_in,
)
from ajtwin.apps.detection.settling import SettlingDetector, switched_on_s
from ajtwin.apps.detection.statistics import normalised_innovations
from ajtwin.io.csv_table import write_csv
from ajtwin.model import STATE_NAMES

#: the data share's columns (:func:`_with_share`), the table's last
SHARE_PREFIXES = ("data_share_", "determined_")

#: the TwinRun.to_frame columns of the vial observer (filled in after the run)
VIAL_COLUMNS = {
    "vial_observed_mL": "vial_ml",
    "vial_observed_mL_std": "vial_std_ml",
    "vial_loss_rate_mL_per_h": "loss_rate_ml_per_h",
    "atomizer_efficiency": "efficiency",
    "vial_running_low": "running_low",
}


@dataclass
class EstimateResult:
    """What ``estimate`` wrote and what the command says about it.

    Attributes
    ----------
    run : TwinRun
        The run (the whole one with ``smooth`` or a plot; else its start, end, θ history).
    rows : int
    mismatch : MismatchStatus
    mean_nis_per_output : float
        Mean of NIS / measured outputs (1 = consistent).
    reinitialised : int
        Times the divergence guard re-initialised the filter.
    undetermined : list of str
        States this print's data did not determine (their bands are the prior's).
    """

    run: object
    rows: int
    mismatch: object
    mean_nis_per_output: float
    reinitialised: int
    undetermined: list = field(default_factory=list)


def estimate_to_csv(
    twin, record, out, *, smooth: bool = False, whole: bool = False, progress=None, job=None
) -> EstimateResult:
    """Run ``twin`` over ``record`` and write the states table to ``out`` (module docstring).

    ``whole``: keep the whole run (a plot of it follows); implied by ``smooth``. ``job``: a
    job print's program (:meth:`~ajtwin.estimation.Twin.run`).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if smooth or whole:
        return _whole(twin, record, out, smooth, progress, job)
    with tempfile.TemporaryDirectory(prefix=".ajtwin-rows-", dir=out.parent) as spill:
        rows = _Rows(Path(spill), switched_on_s(record.meta))
        run = twin.run(record, progress=progress, sink=rows, job=job)
        mismatch = rows.guard_verdict(run)
        # the vial observer once the guard's inputs are let go: the two never held together
        run = replace(run, vial=twin.observe_vial(run))
        rows.write(out, run, mismatch.flags)
    return EstimateResult(
        run,
        rows.n,
        mismatch,
        rows.nis_sum / max(rows.nis_n, 1),
        rows.reinitialised,
        _undetermined(rows.share_end),
    )


def _undetermined(share) -> list:
    return [n for n, v in determined_states(share).items() if not v["determined"]]


def _with_share(frame: pd.DataFrame, share: np.ndarray) -> pd.DataFrame:
    """The data share columns of each state (and whether it is determined), in order."""
    threshold = float(load_guard_settings()["undetermined_share"])
    columns = {}
    for i, name in enumerate(STATE_NAMES):
        columns["data_share_" + name] = share[:, i]
        columns["determined_" + name] = share[:, i] >= threshold
    return pd.concat([frame, pd.DataFrame(columns, index=frame.index)], axis=1)


def _whole(twin, record, out, smooth, progress, job) -> EstimateResult:
    """The run held whole (the smoother needs it, and so does a plot)."""
    run = twin.run(record, smooth=smooth, progress=progress, job=job)
    frame = run.to_frame(smoothed=smooth)
    # the guard: never return states from a model that does not fit without saying so
    mismatch = assess_run(run, record)
    frame["mismatch"] = mismatch.flags
    # which bands this print's data set, and which are the prior's (ΔR_T: no output sees it)
    share = data_share(run.filtered)
    frame = _with_share(frame, share)
    write_csv(frame, out)
    per_output = frame["nis"] / np.maximum(frame["n_measured"], 1)
    return EstimateResult(
        run,
        len(frame),
        mismatch,
        float(np.nanmean(per_output)),
        int(np.asarray(run.filtered.reinitialised).sum()),
        _undetermined(share),
    )


class _Rows:
    """The table's rows, made from each chunk of the run (:meth:`Twin.run`'s sink), and
    what the guard needs of them; written once the run has ended (the guard's flags and
    the vial observer come with the end)."""

    def __init__(self, spill: Path, switched_on: float | None = None):
        # each chunk's rows wait on disk for the end (a week's rows held were ~0.25 GB)
        self.spill = spill
        self.frames: list[Path] = []
        self.guard = GuardInputs()
        self.carry: dict = {}
        self.share_end = None
        self.n = 0
        self.nis_sum, self.nis_n, self.reinitialised = 0.0, 0, 0
        # a print that begins with the atomizer's run-in: when the twin said ready to print
        self.switched_on = switched_on
        self.settling = None if switched_on is None else SettlingDetector()

    def __call__(self, first: int, chunk) -> None:
        """Take the chunk of steps [first, first + n)."""
        frame = chunk.to_frame(smoothed=False)
        share = data_share(chunk.filtered, self.carry)
        self.share_end = share[-1:]
        self.frames.append(self.spill / f"{len(self.frames)}.pkl")
        _with_share(frame, share).to_pickle(self.frames[-1])
        f = chunk.filtered
        # the measurements the filter used (on a job print: the camera's filed at print
        # times), which the run gives with each chunk
        e = normalised_innovations(
            chunk.measurements, np.asarray(f.predicted_outputs), np.asarray(f.innovation_variances)
        )
        after = np.asarray(chunk.time_s, dtype=float) >= (self.switched_on or 0.0)
        if self.settling is not None and after.any():
            self.settling.update(
                np.asarray(chunk.time_s)[after],
                np.asarray(chunk.means)[after],
                np.asarray(f.predicted_outputs)[after],
            )
        run_in = self.settling is not None
        ready = self.settling.readiness.ready_at_s if run_in else None
        e = without_run_in(chunk.time_s, e, run_in, ready)
        self.guard.add(
            chunk.time_s, chunk.means, e, np.asarray(f.nis), np.asarray(f.n_measured), chunk.stds
        )
        per_output = frame["nis"].to_numpy() / np.maximum(frame["n_measured"].to_numpy(), 1)
        self.nis_sum += float(np.nansum(per_output))
        self.nis_n += int(np.isfinite(per_output).sum())
        self.reinitialised += int(frame["reinitialised"].sum())
        self.n += len(frame)

    def guard_verdict(self, run):
        """The mismatch guard over the whole print, from the kept per-second inputs."""
        run_in = self.settling is not None
        ready = self.settling.readiness.ready_at_s if run_in else None
        return self.guard.assess(
            start_mean=run.start_mean,
            start_cov=run.start_cov,
            level_learned_s=settled_level_s(run, run_in, ready),
        )

    def write(self, out: Path, run, flags) -> None:
        """Write the rows, chunk by chunk, with the vial observer's, the guard's and the data
        share's columns in the order :meth:`TwinRun.to_frame` and the guard give them."""
        vial = run.vial
        start = 0
        with open(out, "wb") as fh:
            for path in self.frames:
                frame = pd.read_pickle(path)
                path.unlink()
                stop = start + len(frame)
                columns = {c: frame[c].to_numpy() for c in frame.columns}
                if vial is not None:  # their places in the table, filled in
                    for column, attribute in VIAL_COLUMNS.items():
                        columns[column] = np.asarray(getattr(vial, attribute))[start:stop]
                columns["mismatch"] = np.asarray(flags)[start:stop]
                share = [c for c in columns if c.startswith(SHARE_PREFIXES)]
                last = {c: columns.pop(c) for c in share}
                write_csv({**columns, **last}, fh, header=start == 0)
                start = stop
        self.frames = []
