"""The detectors' settings: thresholds with their provenance (``data/detectors.toml``).

Thresholds are not the textbook ones: the twin's innovations are autocorrelated (the
virtual printer is not the twin's model), so ``drift``/``threshold``/``alpha`` were set on
clean prints (``exp1`` seeds 10–13, ``exp2`` and ``exp3`` seed 10: 9 h with input
steps) and the false-alarm rate is measured on ``clean_long`` (a different scenario and
seed). On top, innovations are Huber-clipped and each CUSUM channel is divided by its
measured long-run σ (:class:`~ajtwin.apps.detection.statistics.LongRunScale`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ajtwin.config import packaged_toml

SHORT_OUTPUT = ("L_w", "L_o", "P_c", "P_s", "Q_m")


#: the CUSUM channels: the five outputs and the common-mode pressure sum
CUSUM_CHANNELS = (*SHORT_OUTPUT, "P_c+P_s")


SHORT_STATE = ("d_a", "V_l", "ΔR_T", "ΔR_N", "φ_A")


def load_detector_settings() -> dict:
    """``data/detectors.toml`` (thresholds with their provenance), flattened to
    :class:`DetectorSettings` field names."""
    data = packaged_toml("data/detectors.toml")
    c, n, ev, r, lr, dp = (
        data[k] for k in ("cusum", "nis", "events", "robust", "long_run", "deposit")
    )
    return {
        "cusum_drift": c["drift"],
        "cusum_threshold": c["threshold"],
        "cusum_threshold_pressure": c["threshold_pressure"],
        "cusum_threshold_material_flow": c["threshold_material_flow"],
        "cusum_drift_material_flow": c["drift_material_flow"],
        "cusum_drift_pressure_sum": c["drift_pressure_sum"],
        "cusum_threshold_pressure_sum": c["threshold_pressure_sum"],
        "nis_window_s": n["window_s"],
        "nis_alpha": n["alpha"],
        "merge_s": ev["merge_s"],
        "merge_other_family_s": ev["merge_other_family_s"],
        "evidence_s": ev["evidence_s"],
        "significance_z": ev["significance_z"],
        "vial_low_mL": ev["vial_low_mL"],
        "warmup_s": ev["warmup_s"],
        "innovation_clip_sigma": r["innovation_clip_sigma"],
        "material_flow_reference_s": r["material_flow_reference_s"],
        "long_run_block_s": tuple(int(b) for b in lr["block_s"]),
        "long_run_blocks": lr["blocks"],
        "long_run_min_blocks": lr["min_blocks"],
        "long_run_max_scale": lr["max_scale"],
        "long_run_reference_pressure_sum": lr["reference_pressure_sum"],
        "deposit_window_s": dp["window_s"],
        "deposit_push_nm": dp["push_nm"],
        **_gap_and_range_settings(data),
    }


def _gap_and_range_settings(data: dict) -> dict:
    """The settings of ``[gaps]`` (detectors after a data gap), ``[nozzle_cleaning]`` (a
    deposit beyond the output model's range) and ``[nis] long_run_scaled`` in
    ``data/detectors.toml``."""
    gaps, cleaning = data["gaps"], data["nozzle_cleaning"]
    return {
        "gap_restart_s": gaps["restart_after_s"],
        "cleaning_deposit_um": cleaning["deposit_um"],
        "nis_long_run_scaled": bool(data["nis"]["long_run_scaled"]),
    }


_D = load_detector_settings()


@dataclass(frozen=True)
class DetectorSettings:
    """Thresholds of the detectors (normalised-innovation units unless said).

    Defaults and why each value: ``data/detectors.toml``.
    """

    cusum_drift: float = _D["cusum_drift"]  # allowance k per step [σ]
    cusum_threshold: float = _D["cusum_threshold"]  # h [σ] for L_w, L_o
    # h [σ] for P_c and P_s on their own (their common mode has its own below)
    cusum_threshold_pressure: float = _D["cusum_threshold_pressure"]
    cusum_threshold_material_flow: float = _D["cusum_threshold_material_flow"]
    cusum_drift_material_flow: float = _D["cusum_drift_material_flow"]
    cusum_drift_pressure_sum: float = _D["cusum_drift_pressure_sum"]  # e_Pc + e_Ps
    cusum_threshold_pressure_sum: float = _D["cusum_threshold_pressure_sum"]
    nis_window_s: int = _D["nis_window_s"]
    nis_alpha: float = _D["nis_alpha"]  # tail probability of the windowed NIS
    merge_s: float = _D["merge_s"]  # alarms within this gap belong to one event ...
    merge_other_family_s: float = _D["merge_other_family_s"]  # ... another family: only this
    evidence_s: float = _D["evidence_s"]  # seconds after detection used for the cause label
    significance_z: float = _D["significance_z"]  # |mean e|·√n above this = output moved
    vial_low_mL: float = _D[
        "vial_low_mL"
    ]  # the low end of H's Box–Behnken fit (model reference §4)
    warmup_s: float = _D["warmup_s"]  # ignore the initial transient of the filter
    innovation_clip_sigma: float = _D["innovation_clip_sigma"]  # Huber clip of e
    # Q_m's CUSUM reference: the print's own level (warm-up mean, then an EWMA with this
    # time constant [s]; 0: e_Qm tested against 0 as before)
    material_flow_reference_s: float = _D["material_flow_reference_s"]
    # each CUSUM channel's increments / its long-run σ (LongRunScale), never by less than 1
    # block lengths [s]: the scale is the largest of their estimates (noise with memory
    # beyond a block looks white to it; a CUSUM integrates over tens of seconds to minutes)
    long_run_block_s: tuple = _D["long_run_block_s"]
    long_run_blocks: int = _D["long_run_blocks"]  # trailing block differences behind it
    long_run_min_blocks: int = _D["long_run_min_blocks"]  # fewer: scale 1
    long_run_max_scale: float = _D["long_run_max_scale"]
    long_run_reference_pressure_sum: float = _D["long_run_reference_pressure_sum"]
    # the filter's push on the nozzle deposit: Σ (x̂_k − x̂_{k|k−1})[ΔR_N] over this window
    # [s] above ``deposit_push_nm`` [nm] = the data keep adding deposit the model does not
    deposit_window_s: int = _D["deposit_window_s"]
    deposit_push_nm: float = _D["deposit_push_nm"]
    # a run of this many seconds without any measurement (a link outage, a gap in a log)
    # restarts the detectors' warm-up at the next measured second
    gap_restart_s: float = _D["gap_restart_s"]
    # the nozzle deposit [µm] beyond which the output model extrapolates: one event
    # "nozzle needs cleaning", and the later alarms of the print join it
    cleaning_deposit_um: float = _D["cleaning_deposit_um"]
    # the windowed NIS from innovations divided by their long-run σ (as the CUSUMs')
    nis_long_run_scaled: bool = _D["nis_long_run_scaled"]


def cusum_thresholds(settings: DetectorSettings) -> np.ndarray:
    """The CUSUM decision intervals h per channel of :data:`CUSUM_CHANNELS` [σ]."""
    s = settings
    return np.array(
        [s.cusum_threshold] * 2
        + [s.cusum_threshold_pressure] * 2
        + [s.cusum_threshold_material_flow, s.cusum_threshold_pressure_sum]
    )
