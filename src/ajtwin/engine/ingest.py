"""Ingest of a finished print: hash, start, twin, detectors, judgement, one transaction.

:func:`ingest_record` runs a machine's twin over one print (a file from the machine's
log or a live print that ended) from the start the machine's chain gives
(:mod:`ajtwin.engine.start`), runs the detectors over the run, judges it
(:func:`ajtwin.engine.chain.judge_run`) and stores everything in one registry
transaction (:func:`save_print`). The live twin's fleet stores a finished live print
through the same :func:`save_print`.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ajtwin.apps.detection.batch import DETECTOR_ARRAYS, detect_run
from ajtwin.apps.detection.mismatch import (
    ChunkedGuard,
    assess_run,
    data_share,
    determined_states,
    first_em_update_s,
    relabel_events,
    run_in_level_s,
    settled_level_s,
    without_run_in,
)
from ajtwin.apps.detection.settling import switched_on_s
from ajtwin.apps.detection.statistics import normalised_innovations
from ajtwin.apps.detection.streaming import AnomalyDetector
from ajtwin.engine.chain import chain_start
from ajtwin.engine.parts import PrintWriter
from ajtwin.engine.print_job import entry_job, job_entry
from ajtwin.engine.start import carried_long_run_history, machine_start
from ajtwin.engine.video import join_video
from ajtwin.estimation.line_speed_fit import teach_speed_law
from ajtwin.estimation.print_time import is_job_record, record_duration_s
from ajtwin.estimation.twin import Twin, first_em_update_time
from ajtwin.io.records import JOB_COLUMNS, SpooledRecord, open_record
from ajtwin.model import STATE_NAMES
from ajtwin.store.registry import NewPrint, RegistryError, record_hash


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
        The run's start, end, θ history, initial fit and visibility (its per-step results
        went to the registry as they were produced); the whole run with ``keep_run``.
    detection : DetectionResult or None
        The detectors' statistics over the print (``keep_run`` only).
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


@dataclass(frozen=True)
class TwinOutcome:
    """What a twin's run over one print concluded, as :func:`save_print` stores it.

    Attributes
    ----------
    arrays : dict
        The run's per-second arrays (:func:`run_arrays`); with a writer, only the θ
        history (the rest went to the registry in parts).
    events : list of AnomalyEvent
    start, end : (mean (5,), cov (5, 5))
    theta_before, theta_after : array (5,)
    started_from : str
        Where the print started (:attr:`ajtwin.engine.chain.ChainStart.description`).
    status, status_reason : str
        :func:`ajtwin.engine.chain.judge_run` of the run.
    extra_summary : dict
        More summary keys (calibration, maintenance, mismatch status).
    long_run_history : dict, optional
        The detectors' long-run statistics for the machine's next print.
    """

    arrays: dict
    events: list
    start: tuple
    end: tuple
    theta_before: object
    theta_after: object
    started_from: str
    status: str
    status_reason: str
    extra_summary: dict = field(default_factory=dict)
    long_run_history: dict | None = None


def save_print(
    registry,
    machine: str,
    record,
    outcome: TwinOutcome,
    *,
    digest: str,
    source: str,
    expected_last_seq,
    live_session: int | None = None,
    keep_live_steps: bool = False,
    writer=None,
    n_samples: int | None = None,
    job: dict | None = None,
):
    """Store a twin's run over one print in one registry transaction; (print id, summary).

    ``outcome``: what the run concluded (:class:`TwinOutcome`);
    ``live_session``/``keep_live_steps``: the live session the print ends, closed in the
    same transaction (:meth:`ajtwin.store.registry.Registry.save_print`);
    ``writer``: a :class:`~ajtwin.engine.parts.PrintWriter` that wrote the per-step arrays
    as they came (closed here; ``outcome.arrays`` then holds the θ history, ``record`` may
    be None with ``n_samples`` given);
    ``job``: the machine program the print ran (:class:`ajtwin.store.registry.NewPrint`).
    """
    arrays, end = outcome.arrays, outcome.end
    if writer is not None:
        writer.close()
        totals = writer.totals
        nis, reinitialised = [totals["mean_nis"]], [totals["reinitialised"]]
    else:
        nis, reinitialised = arrays["nis"], arrays["reinitialised"]
    summary = print_summary(
        end[0],
        end[1],
        nis,
        reinitialised,
        len(outcome.events),
        len(arrays["theta_history_time_s"]),
        outcome.started_from,
        outcome.status,
        outcome.status_reason,
    )
    summary.update(outcome.extra_summary or {})
    meta = {k: v for k, v in record.meta.items() if k != "scenario_config"}
    n = len(record) if n_samples is None else int(n_samples)
    entry = NewPrint(
        content_hash=digest,
        source=source,
        meta=meta,
        summary=summary,
        n_samples=n,
        duration_s=float(record.duration_s + 1.0) if n_samples is None else float(n),
        start_mean=outcome.start[0],
        start_cov=outcome.start[1],
        end_mean=end[0],
        end_cov=end[1],
        theta_before=outcome.theta_before,
        theta_after=outcome.theta_after,
        arrays=arrays,
        anomalies=outcome.events,
        status=outcome.status,
        status_reason=outcome.status_reason,
        long_run_history=outcome.long_run_history,
        job=job,
    )
    print_id = registry.save_print(
        machine,
        entry,
        expected_last_seq=expected_last_seq,
        draft=None if writer is None else writer.draft,
        live_session=live_session,
        keep_live_steps=keep_live_steps,
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
    keep_run: bool = False,
    job: dict | None = None,
):
    """Run the machine's twin over one finished print and store the result.

    Hash the print (duplicate → stop before any work), start from the machine's chain
    (:func:`ajtwin.engine.chain.chain_start`), run the twin (EKF + EM) and the live
    detectors over each chunk of the run, judge it (:func:`ajtwin.engine.chain.judge_run`)
    and store everything in one transaction. Each chunk's arrays are written as produced
    (:class:`IngestSink`, :class:`~ajtwin.engine.parts.PrintWriter`: a draft the final
    transaction adopts), the guard judging each chunk (:class:`ChunkedGuard`).

    Parameters
    ----------
    registry : Registry
    machine : str
        A registered machine name.
    record : PrintRecord or SpooledRecord
        The print (display units; NaN = not measured). Held on disk
        (:func:`ajtwin.io.records.open_record`), it is read a piece at a time
        (:meth:`~ajtwin.estimation.twin.Twin.run_streamed`) unless ``keep_run`` asks for
        the whole run: memory then does not grow with the print.
    source : str
        Where the print came from (file path), stored for the history.
    progress : callable(int), optional
        Steps done, for a progress bar.
    twin_overrides : dict, optional
        :class:`~ajtwin.estimation.twin.TwinConfig` overrides.
    keep_run : bool
        Also return the whole run and detectors' results (memory then grows with the print).
    job : dict, optional
        The program the print ran (:func:`ajtwin.engine.print_job.job_entry`), stored with
        it; on a job print the twin files the camera's frames with it.

    Returns
    -------
    IngestResult (``duplicate=True`` and the existing print when it was ingested before).
    """
    t0 = time.perf_counter()
    if isinstance(record, SpooledRecord) and keep_run:
        record = record.load()  # the whole run is returned: it is held anyway
    digest = record_hash(record)
    existing = registry.find_print(machine, digest)
    if existing is not None:
        return _stored_before(machine, existing, digest, t0)
    chain = chain_start(registry, machine)
    # the machine's calibration, commissioning start and maintenance (model reference §11)
    begin = machine_start(registry, machine, chain, twin_overrides)
    twin = Twin.default(**begin["twin_kwargs"])
    job_run = _printed_job(job, record)
    if begin["speed_exponents"] is not None:
        twin.learn_speed_law(begin["speed_exponents"])
    if job_run is not None:  # the speed law's exponents from this print's camera
        teach_speed_law(twin, record, job_run)
    start, expected = begin["start"], chain.latest_seq
    twin.theta = begin["theta"]
    theta_before = twin.theta.copy()
    writer = PrintWriter(registry, machine, f"ingest of {source or 'a record'}")
    try:
        carried = carried_long_run_history(registry, machine, chain)
        sink = IngestSink(writer, record, detector_settings, carried, keep_run, twin.config)
        run = _run_twin(twin, record, start, progress, sink, job_run)
        events, mismatch = sink.finish(run)
        print_id, summary = save_print(
            registry,
            machine,
            record,
            _ingest_outcome(run, twin, theta_before, begin, sink, events, mismatch),
            digest=digest,
            source=source,
            expected_last_seq=expected,
            writer=writer,
            job=job,
        )
    except RegistryError:
        writer.discard()
        # a concurrent ingest of the same print may have won the race
        existing = registry.find_print(machine, digest)
        if existing is None:
            raise
        return _stored_before(machine, existing, digest, t0)
    except BaseException:
        with contextlib.suppress(RegistryError):
            writer.discard()
        raise
    seq = registry.get_print(print_id)["seq"]
    whole, detection = sink.whole_run(run) if keep_run else (run, None)
    return IngestResult(
        machine,
        print_id,
        seq,
        False,
        digest,
        len(record),
        events=events,
        summary=summary,
        seconds=time.perf_counter() - t0,
        run=whole,
        detection=detection,
    )


def _ingest_outcome(run, twin, theta_before, begin, sink, events, mismatch):
    """What an ingest's run concluded (:class:`TwinOutcome`): the run, the machine's start
    (:func:`~ajtwin.engine.start.machine_start`), the sink's judgement and detectors."""
    return TwinOutcome(
        arrays=theta_history_arrays(run),
        events=events,
        start=(run.start_mean, run.start_cov),
        end=(run.end_mean, run.end_cov),
        theta_before=theta_before,
        theta_after=twin.theta,
        started_from=begin["started_from"],
        status=sink.status[0],
        status_reason=sink.status[1],
        extra_summary={
            "calibration_id": begin["calibration_id"],
            "maintenance": begin["maintenance"],
            "mismatch": mismatch.to_dict(),
            # which states this print's data determined (ΔR_T: the prior's band)
            "data_share": determined_states(sink.share),
            # the speed law's exponents the print ran with: the machine's next print's prior
            "speed_exponents": twin.speed_exponents.to_dict(),
        },
        long_run_history=sink.detector.long_run_history(),
    )


def _run_twin(twin, record, start, progress, sink, job_run):
    """The twin's run over the print into ``sink`` (a job print's frames filed at their print
    times with ``job_run``, the program as printed): a piece at a time from a record held on
    disk, else over the record in memory."""
    if isinstance(record, SpooledRecord):
        return twin.run_streamed(record, start=start, progress=progress, sink=sink, job=job_run)
    return twin.run(record, start=start, progress=progress, sink=sink, job=job_run)


def _stored_before(machine: str, existing: dict, digest: str, t0: float) -> IngestResult:
    """The result of ingesting a print the machine has already (nothing changed)."""
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


class IngestSink:
    """The twin's run over a print taken a chunk at a time (:meth:`Twin.run`'s ``sink``):
    each chunk's arrays to the :class:`~ajtwin.engine.parts.PrintWriter`, its steps through
    the detectors, its data share and the mismatch guard (:class:`~ajtwin.apps.detection.
    mismatch.ChunkedGuard`, which keeps only its windows' last rows).

    Parameters
    ----------
    writer : PrintWriter
    record : PrintRecord
        The print (its measured outputs and inputs for the detectors and the stored arrays).
    settings : DetectorSettings, optional
    long_run_history : dict, optional
        The detectors' carried long-run statistics (:class:`AnomalyDetector`).
    keep : bool
        Keep the chunks too (:meth:`whole_run`).
    twin_config : TwinConfig, optional
        The twin's configuration: when its first EM update takes effect (:func:`~ajtwin.
        estimation.twin.first_em_update_time`), which the guard needs from the first chunk.
        None: a twin without EM.
    """

    def __init__(
        self, writer, record, settings=None, long_run_history=None, keep=False, twin_config=None
    ):
        self.writer = writer
        self.record = record
        # a job print's shutter, speed and print times (stored with the arrays); a record
        # held on disk gives each chunk's rows as they come
        self._job = None
        if record.has_job:
            self._job = record if isinstance(record, SpooledRecord) else record.data
        self.settings, self.long_run_history = settings, long_run_history
        self.detector = AnomalyDetector(settings, long_run_history, switched_on_s(record.meta))
        self.keep = keep
        self.chunks: list = []
        self.share = None  # (1, 5) the data share at the last step so far
        self._share_carry: dict = {}
        self._guard = None  # made at the first chunk, which brings the start prior
        self._level_learned_s = None
        self._config = twin_config
        if twin_config is not None:
            self._level_learned_s = first_em_update_time(twin_config, record.time_s)
        # a print that begins with the atomizer's run-in: its level is learned only once EM
        # has a window after ready to print (settled_level_s), not known before then
        self._run_in = switched_on_s(record.meta) is not None
        self._run_in_level_s = None
        self.status = ("ok", "")

    def __call__(self, first: int, chunk) -> None:
        """Take the chunk of steps [first, first + n) (a TwinRun of them)."""
        stop = first + len(chunk.time_s)
        # the chunk's own inputs and measurements (the run's, not a copy of the record's)
        part = SimpleNamespace(
            outputs=chunk.measurements,
            inputs=chunk.inputs,
            has_job=self._job is not None,
            data=None if self._job is None else self._job_rows(first, stop),
        )
        arrays = run_arrays(chunk, part)
        for step in _detector_steps(self.detector, arrays):
            for event in step.raised:
                self.writer.note_alarm(event.detected_s, event.onset_s)
        self.writer.add(arrays)
        self.share = data_share(chunk.filtered, self._share_carry)[-1:]
        e = normalised_innovations(
            arrays["measurements"], arrays["predicted_outputs"], arrays["innovation_variances"]
        )
        if self._guard is None:
            self._guard = ChunkedGuard(
                start_mean=chunk.start_mean,
                start_cov=chunk.start_cov,
                level_learned_s=self._level_learned_s,
            )
        self._guard_level()
        e = without_run_in(arrays["time_s"], e, self._run_in, self._ready_s())
        self._guard.add(
            arrays["time_s"], arrays["means"], e, arrays["nis"], arrays["n_measured"],
            arrays["stds"],
        )  # fmt: skip
        if self.keep:
            self.chunks.append(chunk)

    def _ready_s(self) -> float | None:
        """When the twin said ready to print after the print's switch-on (None: not yet)."""
        spans = self.detector.run_in.spans
        return spans[0][1] if spans else None

    def _guard_level(self) -> None:
        """On a print that begins with a run-in, the guard's level time: inf until ready to
        print, then the first EM update over a window after it (from the twin's schedule:
        the guard judges each chunk as it comes)."""
        if not self._run_in or self._level_learned_s is None:
            return
        ready = self._ready_s()
        settled = None
        if ready is not None:
            settled = first_em_update_time(self._config, self.record.time_s, ready)
        level = run_in_level_s(self._level_learned_s, settled, True, ready)
        self._run_in_level_s = level
        self._guard.learn_level_from(level)

    def _job_rows(self, first: int, stop: int):
        if isinstance(self._job, SpooledRecord):
            return self._job.piece(first, stop).data[list(JOB_COLUMNS)]
        return self._job[list(JOB_COLUMNS)].iloc[first:stop]

    def finish(self, run) -> tuple[list, object]:
        """(the print's events, the mismatch guard's verdict) once the run is done; the
        events a mismatch explains relabelled, the print judged (:attr:`status`)."""
        events = self.detector.finish()
        if first_em_update_s(run) != self._level_learned_s:
            raise RuntimeError(
                f"the twin's first EM update came at {first_em_update_s(run)} s, not at "
                f"{self._level_learned_s} s as the mismatch guard was told: its Q_m level "
                "test would be wrong"
            )
        settled = settled_level_s(run, self._run_in, self._ready_s())
        if self._run_in and self._run_in_level_s != settled:
            raise RuntimeError(
                f"the twin's first EM update after ready to print came at {settled} s, not at "
                f"{self._run_in_level_s} s as the mismatch guard was told"
            )
        mismatch = self._guard.finish()
        # a model that does not fit the machine is reported as such, never as a fault
        events = relabel_events(events, mismatch)
        for event in events:
            self.writer.note_alarm(event.detected_s, event.onset_s)
        self.status = self.writer.judgement(run.start_mean)
        return events, mismatch

    def whole_run(self, run):
        """(the whole TwinRun, the detectors' DetectionResult) from the kept chunks."""
        parts = [c.filtered for c in self.chunks]
        whole = replace(
            run,
            filtered=type(parts[0])(*[np.concatenate(x, axis=0) for x in zip(*parts)]),
            theta_per_step=np.concatenate([c.theta_per_step for c in self.chunks]),
            calibration_covariances=_joined(self.chunks, "calibration_covariances"),
            prior_floor=_joined(self.chunks, "prior_floor"),
        )
        detection = detect_run(whole, self.record, self.settings, self.long_run_history)
        detection.events = relabel_events(detection.events, assess_run(whole, self.record))
        return whole, detection


def _joined(chunks, name):
    parts = [getattr(c, name) for c in chunks]
    return None if any(p is None for p in parts) else np.concatenate(parts, axis=0)


def _detector_steps(detector, arrays):
    """The detectors' steps over a chunk's arrays (run_arrays names)."""
    columns = [arrays[k] for k in DETECTOR_ARRAYS[1:]]  # all but the time
    for k, t in enumerate(arrays["time_s"]):
        yield detector.update(t, *(c[k] for c in columns), inputs=arrays["inputs"][k])


def theta_history_arrays(run) -> dict:
    """The θ history of a run, as the registry keeps it with the print's row."""
    hist = run.theta_history
    return {
        "theta_history_time_s": hist["time_s"].to_numpy(float),
        "theta_history": hist[[c for c in hist.columns if c.startswith("theta_")]].to_numpy(float),
    }


def _printed_job(entry: dict | None, record):
    """The job a job record's print ran (from the entry kept with it), for the twin to file
    the camera's frames with; None without an entry or for a record without job columns.
    A looped program is answered run by run (:class:`ajtwin.job.LoopedJob`): the filing asks
    only where the stage is and what lies under the camera, and the print may last days."""
    if entry is None or not is_job_record(record):
        return None
    return entry_job(entry, print_duration_s=record_duration_s(record), held=False)


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
    switched_on_s: float | None = None,
):
    """Read a print file (and optionally its video) and :func:`ingest_record` it.

    ``aliases``, ``dialect``: as :func:`ajtwin.io.records.read_record`. ``program``: the
    machine program the print ran, kept with it; ``job_options``: keywords of
    :func:`ajtwin.engine.print_job.job_entry` (speeds, looping, tolerance). The program is
    read and checked against the record before the twin runs. ``switched_on_s``: when the
    atomizer was switched on, in place of the record's ``atomizer_switched_on_s``.
    """
    path = Path(path)
    with open_record(path, aliases=aliases, dialect=dialect) as spooled:
        if switched_on_s is not None:
            spooled.meta["atomizer_switched_on_s"] = float(switched_on_s)
        job = None if program is None else job_entry(program, spooled, **(job_options or {}))
        if video is None:
            # read a piece at a time by the twin: memory does not grow with the print
            return ingest_record(
                registry, machine, spooled, source=str(path), progress=progress, job=job
            )
        record = spooled.load()
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
