"""Commissioning a machine as one workflow: fit, learn its noise scale, store (model reference §11).

1. :func:`commission_machine` fits the machine's calibration from a commissioning print
   (:func:`ajtwin.estimation.commission.commission`) and runs the commissioned twin over
   the same print, as it will run over the next one, for the detectors' long-run
   statistics (:func:`commissioning_long_run_history`): the machine's next print starts
   with its own noise scale (its gauges' wander, its camera) instead of 1.
2. :func:`save_commissioning` stores both in the registry (a new calibration row; the
   history is kept); :func:`write_calibration` writes the calibration as a TOML file for
   ``ajtwin estimate --calibration``.
3. The machine's next print starts where commissioning left it
   (:func:`commissioned_start`) with the commissioned twin (:func:`calibrated_twin`) —
   what :func:`ajtwin.engine.start.machine_start` does for a registered machine.

Examples
--------
>>> from ajtwin.simulation import simulate                          # doctest: +SKIP
>>> done = commission_machine(simulate("commissioning", seed=1))   # doctest: +SKIP
>>> twin, start = calibrated_twin(done.result), commissioned_start(done.result)  # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.engine.chain import carry_over
from ajtwin.estimation.commission import (
    CommissioningResult,
    commission,
    unpinned_aerosol_level,
)
from ajtwin.estimation.twin import Twin
from ajtwin.store.calibration import save_calibration


@dataclass
class Commissioning:
    """A commissioned machine: its calibration and its detectors' long-run statistics.

    Attributes
    ----------
    result : CommissioningResult
        The fitted calibration with its standard errors and the machine's end state.
    long_run_history : dict or None
        The detectors' long-run statistics on the commissioning print
        (:meth:`ajtwin.apps.detection.streaming.AnomalyDetector.long_run_history`).
    """

    result: CommissioningResult
    long_run_history: dict | None


def calibrated_twin(result: CommissioningResult) -> Twin:
    """The twin of a commissioned machine: its calibration, covariance and noise factors,
    with θ_φA holding the atomizer's level when commissioning pinned it."""
    twin = Twin.default(**calibration_twin_kwargs(result))
    twin.theta[4] = aerosol_level(result).get("theta_per_s", 0.0)
    return twin


def aerosol_level(calibrated) -> dict:
    """φ_A's level of a calibration (:attr:`CommissioningResult.aerosol_level`; for a stored
    row, its ``priors``' ``aerosol_level``); a calibration stored without one: the
    generation model's ± its prior (:func:`unpinned_aerosol_level`)."""
    if isinstance(calibrated, dict):
        level = (calibrated.get("priors") or {}).get("aerosol_level")
    else:
        level = calibrated.aerosol_level
    return dict(level) if level else unpinned_aerosol_level()


def calibration_twin_kwargs(calibrated) -> dict:
    """:meth:`Twin.default` keywords of a calibration: a :class:`CommissioningResult` or a
    stored calibration row (:func:`ajtwin.store.calibration.active_calibration`)."""
    level = aerosol_level(calibrated).get("relative_std", 0.0)
    if isinstance(calibrated, dict):
        return {
            "calibration": calibrated["calibration"],
            "calibration_cov": calibrated["calibration_cov"],
            "noise_factors": calibrated.get("noise_factors"),
            "aerosol_level_std": level,
        }
    return {
        "calibration": calibrated.calibration,
        "calibration_cov": calibrated.calibration_cov,
        "noise_factors": calibrated.noise_factors,
        "aerosol_level_std": level,
    }


def commissioned_start(result: CommissioningResult) -> tuple[np.ndarray, np.ndarray]:
    """Start (mean (5,), cov (5, 5)) of the machine's next print: where commissioning left
    it, with the fast states widened between prints (:func:`ajtwin.engine.chain.carry_over`)."""
    return carry_over(result.end_state, result.end_state_cov)


def commissioning_long_run_history(
    record, result: CommissioningResult, settings: DetectorSettings | None = None
) -> dict:
    """The detectors' long-run statistics of a machine from its commissioning print.

    The commissioned twin runs over the print it was fitted from, as it will run over the
    next one, and the detectors' block differences are returned
    (:meth:`~ajtwin.apps.detection.streaming.AnomalyDetector.long_run_history`). The input
    steps of a commissioning print move single block means, which the robust scale ignores.

    Parameters
    ----------
    record : PrintRecord
        The commissioning print.
    result : CommissioningResult
        Its calibration.
    settings : DetectorSettings, optional
        Detector settings (default: ``data/detectors.toml``).
    """
    return detect_run(calibrated_twin(result).run(record), record, settings).long_run_history


def commission_machine(
    record,
    *,
    known: dict | None = None,
    vial_fill_ml: float = 1.0,
    vial_used_ml: tuple | None = None,
    where: str = "",
    learn_noise_scale: bool = True,
) -> Commissioning:
    """Fit a machine's calibration from a commissioning print and learn its noise scale.

    Parameters
    ----------
    record : PrintRecord
        A print from a cleaned nozzle and a known fill that steps Q_c, Q_s (and I_A)
        across the operating window.
    known : dict, optional
        States known at the start, {name: (mean, std)} in display units (e.g. d_a from a
        droplet sizer).
    vial_fill_ml : float
        The weighed fill [mL].
    vial_used_ml : (mean, std), optional
        The ink the print drew [mL] (the vial weighed before and after): pins φ_A's level.
    where : str
        The print's file, for error messages.
    learn_noise_scale : bool
        Also run the commissioned twin over the print for the detectors' long-run
        statistics (False: ``long_run_history`` is None; a calibration written to a file
        only does not need them).

    Raises
    ------
    CommissioningError
        A print that cannot determine the calibration.
    """
    result = commission(
        record, known=known, vial_fill_ml=vial_fill_ml, vial_used_ml=vial_used_ml, where=where
    )
    history = commissioning_long_run_history(record, result) if learn_noise_scale else None
    return Commissioning(result, history)


def save_commissioning(registry, machine: str, commissioning: Commissioning, source: str) -> int:
    """Store a commissioning as the machine's active calibration; returns its id."""
    return save_calibration(
        registry,
        machine,
        commissioning.result,
        source,
        long_run_history=commissioning.long_run_history,
    )


def write_calibration(path, result: CommissioningResult, provenance: dict) -> Path:
    """Write a commissioning's calibration (with covariance and noise factors) as TOML."""
    return result.write_toml(path, provenance)
