"""Ingest a print into a machine's twin: run it from the machine's last state, store all.

:func:`ingest_record` is the whole step: hash the print (duplicate → stop before any
work), take the machine's last end state and θ (or the initial-state fit for its first
print), optionally fill linewidth/overspray from the alignment-camera video, run the twin
(EKF + EM), run the anomaly detectors on its innovations, and store everything in one
transaction.

Which print the next one starts from, how the fast states' variance is widened between
prints and when a print is kept out of the chain (a state outside the physical range):
:mod:`ajtwin.store.chain`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ajtwin.store.chain import BETWEEN_PRINT_STD, carry_over, chain_start, judge_run
from ajtwin.store.registry import Registry, RegistryError, record_hash

__all__ = ["BETWEEN_PRINT_STD", "carry_over", "ingest_record", "ingest_file", "join_video"]


@dataclass
class IngestResult:
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


def join_video(
    record, video, um_per_px: float, *, progress: bool = True, fps=None, annotate_times=()
):
    """Fill the record's linewidth/overspray from an alignment-camera video (ajtwin.vision).

    Parameters
    ----------
    record : PrintRecord
    video : path of the video (or image folder)
    um_per_px : float, camera pixel size on the substrate [µm]
    annotate_times : sequence of float, optional
        Video times [s] of frames to return annotated (paper's Fig. annotated_acam).

    Returns
    -------
    record : PrintRecord with linewidth_um/overspray_um from the video (NaN where no frame)
    summary : dict, the join counts
    features : DataFrame, one row per frame (``ajtwin extract`` columns)
    annotated : dict {frame time [s]: BGR image}
    """
    import pandas as pd
    from tqdm import tqdm

    from ajtwin.io.records import PrintRecord
    from ajtwin.vision.extract import LineExtractor, annotate, open_source
    from ajtwin.vision.join import check_linewidth_scale, join_features

    frames = open_source(video, fps=fps)
    extractor = LineExtractor(um_per_px)
    wanted = sorted(float(t) for t in annotate_times)
    annotated = {}
    rows = []
    for index, time_s, gray in tqdm(
        frames, total=frames.count, unit="frame", desc="extract video", disable=not progress
    ):
        result = extractor.process(gray, index=index, time_s=time_s)
        rows.append(result.row())
        if wanted and time_s >= wanted[0]:
            annotated[float(time_s)] = annotate(gray, result)
            wanted.pop(0)
    features = pd.DataFrame(rows)
    if (
        features.empty
        or not features["status"].isin(("ok", "ok_std_fallback", "few_batches")).any()
    ):
        counts = features["status"].value_counts().to_dict() if len(features) else {}
        raise ValueError(f"{video}: no frame gave a linewidth (statuses: {counts})")
    good = features["status"].isin(("ok", "ok_std_fallback", "few_batches"))
    check_linewidth_scale(features.loc[good, "linewidth_um"], um_per_px, video)
    joined, summary = join_features(
        record.data,
        features,
        platen_speed_mm_s=float(record.meta.get("platen_speed_mm_s", 1.0)),
    )
    meta = dict(record.meta)
    meta["vision"] = {"video": str(video), **summary}
    return PrintRecord(joined, meta), summary, features, annotated


def ingest_record(
    registry: Registry,
    machine: str,
    record,
    *,
    source: str = "",
    progress=None,
    twin_overrides: dict | None = None,
    detector_settings=None,
) -> IngestResult:
    """Run the machine's twin over one print and store the result (see module docstring).

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

    Returns
    -------
    IngestResult (``duplicate=True`` and the existing print when it was ingested before).
    """
    from ajtwin.apps.anomaly import detect_run
    from ajtwin.estimation import Twin

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
    from ajtwin.store.calibration import active_calibration, apply_maintenance, pending_maintenance

    # --- chain (ajtwin.store.chain): start from the newest good print, never a bad one
    chain = chain_start(registry, machine)
    start, expected = chain.start, chain.latest_seq
    theta = np.zeros(5) if chain.theta is None else np.asarray(chain.theta, dtype=float)
    started_from = chain.description
    # the machine's calibration (SPEC §11): None = never commissioned, the nominal model
    active = active_calibration(registry, machine)
    overrides = dict(twin_overrides or {})
    calibration = None if active is None else active["calibration"]
    latest = 0 if chain.latest_seq is None else chain.latest_seq
    since = 0.0
    if active is not None and active["after_print_seq"] >= latest:
        # commissioned since the last print: start where commissioning left the machine
        start = carry_over(active["end_mean"], active["end_cov"])
        since = active["created_unix"]
        started_from = f"commissioning {active['id']}"
    events = pending_maintenance(registry, machine, since)
    if events:
        if start is None:
            refills = [e["vial_refilled_ml"] for e in events if e["vial_refilled_ml"] is not None]
            if refills:
                overrides.setdefault("vial_fill_ml", refills[-1])
        else:
            mean, cov, theta = apply_maintenance(start[0], start[1], theta, events)
            start = (mean, cov)
        started_from += " + maintenance"
    calibration_cov = None if active is None else active["calibration_cov"]
    noise_factors = None if active is None else active.get("noise_factors")
    twin = Twin.default(
        calibration=calibration,
        calibration_cov=calibration_cov,
        noise_factors=noise_factors,
        **overrides,
    )
    twin.theta = theta
    theta_before = twin.theta.copy()
    run = twin.run(record, start=start, progress=progress)
    status, status_reason = judge_run(run)
    # --- end chain
    detection = detect_run(run, record, detector_settings)
    from ajtwin.apps.mismatch import assess_run, relabel_events

    # a model that does not fit the machine is reported as such, never as a fault
    mismatch = assess_run(run, record)
    detection.events = relabel_events(detection.events, mismatch)

    f = run.filtered
    arrays = {
        "time_s": run.time_s,
        "means": run.means,
        "stds": run.stds,
        "covariances": np.asarray(f.covariances),
        "predicted_means": np.asarray(f.predicted_means),
        "predicted_outputs": np.asarray(f.predicted_outputs),
        "innovation_variances": np.asarray(f.innovation_variances),
        "measurements": record.outputs,
        "inputs": record.inputs,
        "nis": np.asarray(f.nis),
        "n_measured": np.asarray(f.n_measured),
        "reinitialised": np.asarray(f.reinitialised),
        "theta_per_step": run.theta_per_step,
        "mismatch": mismatch.flags,
    }
    hist = run.theta_history
    arrays["theta_history_time_s"] = hist["time_s"].to_numpy(float)
    arrays["theta_history"] = hist[[c for c in hist.columns if c.startswith("theta_")]].to_numpy(
        float
    )
    summary = {
        "end_state": dict(
            zip(
                (
                    "droplet_diameter_um",
                    "vial_volume_mL",
                    "tube_deposition_um",
                    "nozzle_deposition_um",
                    "aerosol_fraction",
                ),
                np.asarray(run.end_mean).tolist(),
            )
        ),
        "end_std": np.sqrt(np.diag(run.end_cov)).tolist(),
        "mean_nis": float(np.nanmean(np.asarray(f.nis))),
        "n_anomalies": len(detection.events),
        "em_updates": int(len(hist)),
        "guard_reinitialisations": int(np.asarray(f.reinitialised).sum()),
        "started_from": started_from,
        "status": status,
        "status_reason": status_reason,
        "calibration_id": None if active is None else int(active["id"]),
        "maintenance": events,
        "mismatch": mismatch.to_dict(),
    }
    meta = {k: v for k, v in record.meta.items() if k != "scenario_config"}
    if run.initial is not None:
        start_mean, start_cov = run.start_mean, run.start_cov
    else:
        start_mean, start_cov = start
    try:
        print_id = registry.save_print(
            machine,
            content_hash=digest,
            source=source,
            meta=meta,
            summary=summary,
            n_samples=len(record),
            duration_s=float(record.duration_s + 1.0),
            start_mean=start_mean,
            start_cov=start_cov,
            end_mean=run.end_mean,
            end_cov=run.end_cov,
            theta_before=theta_before,
            theta_after=twin.theta,
            arrays=arrays,
            anomalies=detection.events,
            expected_last_seq=expected,
            status=status,
            status_reason=status_reason,
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


def ingest_file(
    registry: Registry,
    machine: str,
    path,
    *,
    video=None,
    um_per_px=None,
    progress=None,
    video_progress: bool = True,
) -> IngestResult:
    """Read a print file (and optionally its video) and :func:`ingest_record` it."""
    from ajtwin.io.records import read_record

    path = Path(path)
    record = read_record(path)
    source = str(path)
    if video is not None:
        if um_per_px is None:
            raise ValueError("--video needs --um-per-px (the camera's pixel size on the substrate)")
        record, *_ = join_video(record, video, um_per_px, progress=video_progress)
        source += f" + {video}"
    return ingest_record(registry, machine, record, source=source, progress=progress)
