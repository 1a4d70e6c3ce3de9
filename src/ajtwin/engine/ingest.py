"""Ingest of a finished print: hash, start, twin, detectors, judgement, one transaction.

:func:`ingest_record` runs a machine's twin over one print (a file from the machine's
log or a live print that ended) from the start the machine's chain gives
(:mod:`ajtwin.engine.start`), runs the detectors over the run, judges it
(:func:`ajtwin.engine.chain.judge_run`) and stores everything in one registry
transaction (:func:`save_print`). The live twin's fleet stores a finished live print
through the same :func:`save_print`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.mismatch import assess_run, data_share, determined_states, relabel_events
from ajtwin.engine.chain import chain_start, judge_run
from ajtwin.engine.print_job import entry_job, job_entry
from ajtwin.engine.start import carried_long_run_history, machine_start
from ajtwin.engine.video import join_video
from ajtwin.estimation.print_time import is_job_record, record_duration_s
from ajtwin.estimation.twin import Twin
from ajtwin.io.records import JOB_COLUMNS, read_record
from ajtwin.model import STATE_NAMES
from ajtwin.store.registry import RegistryError, record_hash


@dataclass
class IngestResult:
    """What an ingest did.

    Attributes
    ----------
    machine : str
    print_id, seq : int
        The stored print (the existing one for a duplicate).
    duplicate : bool
        The print was ingested before (nothing changed).
    content_hash : str
    n_samples : int
    events : list of AnomalyEvent
    summary : dict
        The summary the registry keeps.
    seconds : float
        Wall time of the ingest.
    run : TwinRun or None
    detection : DetectionResult or None
    """

    machine: str
    print_id: int
    seq: int
    duplicate: bool
    content_hash: str
    n_samples: int
    events: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
    run: object = None  # TwinRun (None for a duplicate)
    detection: object = None  # DetectionResult (None for a duplicate)


def print_summary(
    end_mean,
    end_cov,
    nis,
    reinitialised,
    n_anomalies: int,
    em_updates: int,
    started_from: str,
    status: str,
    status_reason: str,
):
    """The summary the registry keeps for a print."""
    return {
        "end_state": dict(zip(STATE_NAMES, np.asarray(end_mean, dtype=float).tolist())),
        "end_std": np.sqrt(np.diag(np.asarray(end_cov, dtype=float))).tolist(),
        "mean_nis": float(np.nanmean(np.asarray(nis, dtype=float))),
        "n_anomalies": int(n_anomalies),
        "em_updates": int(em_updates),
        "guard_reinitialisations": int(np.asarray(reinitialised).sum()),
        "started_from": started_from,
        "status": status,
        "status_reason": status_reason,
    }


def save_print(
    registry,
    machine: str,
    record,
    *,
    digest: str,
    source: str,
    arrays: dict,
    events: list,
    start,
    end,
    theta_before,
    theta_after,
    expected_last_seq,
    started_from: str,
    status: str,
    status_reason: str,
    extra_summary: dict | None = None,
    live_session: int | None = None,
    keep_live_steps: bool = False,
    long_run_history: dict | None = None,
    job: dict | None = None,
):
    """Store a twin's run over one print in one registry transaction; (print id, summary).

    ``status``/``status_reason``: :func:`ajtwin.engine.chain.judge_run` of the run;
    ``extra_summary``: more summary keys (calibration, maintenance, mismatch status);
    ``live_session``/``keep_live_steps``: the live session the print ends, closed in the
    same transaction (:meth:`ajtwin.store.registry.Registry.save_print`);
    ``long_run_history``: the detectors' long-run statistics for the machine's next print;
    ``job``: the machine program the print ran (:meth:`ajtwin.store.registry.Registry.save_print`).
    """
    summary = print_summary(
        end[0],
        end[1],
        arrays["nis"],
        arrays["reinitialised"],
        len(events),
        len(arrays["theta_history_time_s"]),
        started_from,
        status,
        status_reason,
    )
    summary.update(extra_summary or {})
    meta = {k: v for k, v in record.meta.items() if k != "scenario_config"}
    print_id = registry.save_print(
        machine,
        content_hash=digest,
        source=source,
        meta=meta,
        summary=summary,
        n_samples=len(record),
        duration_s=float(record.duration_s + 1.0),
        start_mean=start[0],
        start_cov=start[1],
        end_mean=end[0],
        end_cov=end[1],
        theta_before=theta_before,
        theta_after=theta_after,
        arrays=arrays,
        anomalies=events,
        expected_last_seq=expected_last_seq,
        status=status,
        status_reason=status_reason,
        live_session=live_session,
        keep_live_steps=keep_live_steps,
        long_run_history=long_run_history,
        job=job,
    )
    return print_id, summary


def ingest_record(
    registry,
    machine: str,
    record,
    *,
    source: str = "",
    progress=None,
    twin_overrides: dict | None = None,
    detector_settings=None,
    job: dict | None = None,
):
    """Run the machine's twin over one finished print and store the result.

    Hash the print (duplicate → stop before any work), start from the machine's chain
    (:func:`ajtwin.engine.chain.chain_start`: the newest good print's end state and θ; the
    initial-state fit for its first print), run the twin (EKF + EM, :meth:`Twin.run`) and
    the detectors (:func:`~ajtwin.apps.detection.batch.detect_run`, the live detectors over the
    arrays), judge the run (:func:`ajtwin.engine.chain.judge_run`) and store everything in
    one transaction.

    Parameters
    ----------
    registry : Registry
    machine : str
        A registered machine name.
    record : PrintRecord
        The print (display units; NaN = not measured).
    source : str
        Where the print came from (file path), stored for the history.
    progress : callable(int), optional
        Steps done, for a progress bar.
    twin_overrides : dict, optional
        :class:`~ajtwin.estimation.twin.TwinConfig` overrides.
    job : dict, optional
        The program the print ran (:func:`ajtwin.engine.print_job.job_entry`), stored with
        it; on a job print the twin files the camera's frames with it.

    Returns
    -------
    IngestResult (``duplicate=True`` and the existing print when it was ingested before).
    """
    t0 = time.perf_counter()
    digest = record_hash(record)
    existing = registry.find_print(machine, digest)
    if existing is not None:
        return IngestResult(
            machine,
            existing["id"],
            existing["seq"],
            True,
            digest,
            existing["n_samples"],
            summary=existing["summary"],
            seconds=time.perf_counter() - t0,
        )
    chain = chain_start(registry, machine)
    # the machine's calibration, commissioning start and maintenance (model reference §11)
    begin = machine_start(registry, machine, chain, twin_overrides)
    twin = Twin.default(**begin["twin_kwargs"])
    start, expected = begin["start"], chain.latest_seq
    twin.theta = begin["theta"]
    theta_before = twin.theta.copy()
    run = twin.run(record, start=start, progress=progress, job=_printed_job(job, record))
    status, status_reason = judge_run(run)
    detection = detect_run(
        run, record, detector_settings, carried_long_run_history(registry, machine, chain)
    )
    # a model that does not fit the machine is reported as such, never as a fault
    mismatch = assess_run(run, record)
    detection.events = relabel_events(detection.events, mismatch)

    try:
        print_id, summary = save_print(
            registry,
            machine,
            record,
            digest=digest,
            source=source,
            arrays=run_arrays(run, record),
            events=detection.events,
            start=(run.start_mean, run.start_cov),
            end=(run.end_mean, run.end_cov),
            theta_before=theta_before,
            theta_after=twin.theta,
            expected_last_seq=expected,
            started_from=begin["started_from"],
            status=status,
            status_reason=status_reason,
            extra_summary={
                "calibration_id": begin["calibration_id"],
                "maintenance": begin["maintenance"],
                "mismatch": mismatch.to_dict(),
                # which states this print's data determined (ΔR_T: the prior's band)
                "data_share": determined_states(data_share(run.filtered)),
            },
            long_run_history=detection.long_run_history,
            job=job,
        )
    except RegistryError:
        # a concurrent ingest of the same print may have won the race
        existing = registry.find_print(machine, digest)
        if existing is None:
            raise
        return IngestResult(
            machine, existing["id"], existing["seq"], True, digest, existing["n_samples"]
        )
    seq = registry.get_print(print_id)["seq"]
    return IngestResult(
        machine,
        print_id,
        seq,
        False,
        digest,
        len(record),
        events=detection.events,
        summary=summary,
        seconds=time.perf_counter() - t0,
        run=run,
        detection=detection,
    )


def _printed_job(entry: dict | None, record):
    """The job a job record's print ran (from the entry kept with it), for the twin to file
    the camera's frames with; None without an entry or for a record without job columns."""
    if entry is None or not is_job_record(record):
        return None
    return entry_job(entry, print_duration_s=record_duration_s(record))


def run_arrays(run, record) -> dict:
    """The per-second arrays the registry keeps of a twin run over a print (names as
    :meth:`ajtwin.store.registry.Registry.print_arrays` returns them). ``measurements`` are
    those the filter used: on a job print, the camera's filed at their print times, with
    their speed-law factors (``line_factors``) so that the run can be made again."""
    f = run.filtered
    hist = run.theta_history
    measured = getattr(run, "measurements", None)
    line = getattr(run, "line_factors", None)
    return {
        "time_s": run.time_s,
        "means": run.means,
        "stds": run.stds,
        "covariances": np.asarray(f.covariances),
        "predicted_means": np.asarray(f.predicted_means),
        "predicted_outputs": np.asarray(f.predicted_outputs),
        "innovation_variances": np.asarray(f.innovation_variances),
        "measurements": record.outputs if measured is None else measured,
        "inputs": record.inputs,
        "nis": np.asarray(f.nis),
        "n_measured": np.asarray(f.n_measured),
        "reinitialised": np.asarray(f.reinitialised),
        "theta_per_step": run.theta_per_step,
        "theta_history_time_s": hist["time_s"].to_numpy(float),
        "theta_history": hist[[c for c in hist.columns if c.startswith("theta_")]].to_numpy(float),
        # a job print's shutter, speed and print times as the machine logged them
        **(
            {c: record.data[c].to_numpy(dtype=float) for c in JOB_COLUMNS} if record.has_job else {}
        ),
        **({} if line is None else {"line_factors": np.asarray(line, dtype=float)}),
    }


def ingest_file(
    registry,
    machine: str,
    path,
    *,
    video=None,
    um_per_px=None,
    progress=None,
    video_progress: bool = True,
    aliases=None,
    dialect=None,
    program=None,
    job_options: dict | None = None,
):
    """Read a print file (and optionally its video) and :func:`ingest_record` it.

    ``aliases``, ``dialect``: as :func:`ajtwin.io.records.read_record`. ``program``: the
    machine program the print ran, kept with it; ``job_options``: keywords of
    :func:`ajtwin.engine.print_job.job_entry` (speeds, looping, tolerance). The program is
    read and checked against the record before the twin runs.
    """
    path = Path(path)
    record = read_record(path, aliases=aliases, dialect=dialect)
    job = None if program is None else job_entry(program, record, **(job_options or {}))
    source = str(path)
    if video is not None:
        if um_per_px is None:
            raise ValueError("--video needs --um-per-px (the camera's pixel size on the substrate)")
        record, *_ = join_video(record, video, um_per_px, progress=video_progress)
        source += f" + {video}"
    return ingest_record(registry, machine, record, source=source, progress=progress, job=job)


def detector_inputs(registry, print_id: int) -> dict:
    """Keyword arguments of :func:`ajtwin.apps.detection.batch.detect_anomalies` for a stored
    print: what re-running the detectors needs (they use P_k's diagonal only, so
    where the full sequence is not kept it is diag(σ_k²) from the stored σ)."""
    a = registry.print_arrays(print_id)
    if "covariances" in a:
        covariances = a["covariances"]
    else:
        covariances = np.einsum("ti,ij->tij", a["stds"] ** 2, np.eye(a["stds"].shape[1]))
    return {
        "time_s": a["time_s"],
        "measurements": a["measurements"],
        "predicted_outputs": a["predicted_outputs"],
        "innovation_variances": a["innovation_variances"],
        "nis": a["nis"],
        "n_measured": a["n_measured"],
        "means": a["means"],
        "predicted_means": a["predicted_means"],
        "covariances": covariances,
        # the vial observer's inputs; older prints without them: twin's V_l
        "inputs": a.get("inputs"),
    }
