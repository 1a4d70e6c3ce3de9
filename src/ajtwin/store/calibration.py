"""Per-machine calibrations and maintenance events in the registry (model reference §11).

Two tables of the registry (schema migration 4, :mod:`ajtwin.store.schema`; export,
import, copy and compact carry them like the prints), read and written through the
registry's methods:

* ``calibrations`` — every commissioning of a machine with its provenance: the print it
  was fitted from, when, the priors, the standard errors, which parameters the print
  determined, and the machine's state when commissioning ended. The newest row is the
  active calibration; re-commissioning adds a row, so the history is kept.
* ``maintenance_events`` — nozzle cleaned, vial refilled, θ reset: applied to the start
  state of the next ingested print and kept as history.

Persist and read only: the fitting lives in :mod:`ajtwin.estimation.commission`.

Examples
--------
>>> import tempfile, os
>>> from ajtwin.store.registry import Registry
>>> reg = Registry(os.path.join(tempfile.mkdtemp(), "r.sqlite"))
>>> _ = reg.add_machine("aj1")
>>> active_calibration(reg, "aj1") is None
True
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from ajtwin.model.calibration import calibration_from_dict, calibration_to_dict


def save_calibration(
    registry, machine: str, result, source: str, long_run_history: dict | None = None
) -> int:
    """Store a :class:`~ajtwin.estimation.commission.CommissioningResult`; returns its id.

    ``long_run_history``: the detectors' long-run statistics on the commissioning print
    (:func:`ajtwin.engine.commissioning.commissioning_long_run_history`), carried to the next print.
    """
    row = {
        "source": source,
        "calibration_json": json.dumps(calibration_to_dict(result.calibration)),
        "std_json": json.dumps(result.std),
        "prior_std_json": json.dumps(result.prior_std),
        "determined_json": json.dumps(result.determined),
        # φ_A's level (what pinned it) rides with the priors: no schema change
        "priors_json": json.dumps(
            {**result.priors, "aerosol_level": getattr(result, "aerosol_level", {})}
        ),
        "notes_json": json.dumps(result.notes),
        "end_mean_json": json.dumps(np.asarray(result.end_state, float).tolist()),
        "end_cov_json": json.dumps(np.asarray(result.end_state_cov, float).tolist()),
        "calibration_cov_json": json.dumps(np.asarray(result.calibration_cov, float).tolist()),
        "noise_factors_json": json.dumps(
            None if result.noise_factors is None else np.asarray(result.noise_factors).tolist()
        ),
        "long_run_json": json.dumps(long_run_history),
    }
    return registry.add_calibration(machine, row)


def _calibration_row(row) -> dict:
    out = dict(row)
    for key in list(out):
        if key.endswith("_json"):
            out[key.removesuffix("_json")] = json.loads(out.pop(key))
    out["calibration"] = calibration_from_dict(out["calibration"], "registry calibration")
    out["end_mean"] = np.asarray(out["end_mean"], float)
    out["end_cov"] = np.asarray(out["end_cov"], float)
    out["calibration_cov"] = np.asarray(out["calibration_cov"], float)
    return out


def active_calibration(registry, machine: str) -> dict | None:
    """The newest calibration of a machine (dict with ``calibration``, provenance) or None."""
    rows = registry.calibrations(machine, newest_only=True)
    return _calibration_row(rows[0]) if rows else None


def calibration_by_id(registry, calibration_id: int) -> dict | None:
    """The calibration row ``calibration_id`` (as :func:`active_calibration` gives it), or
    None when there is none (a print names the calibration it ran with)."""
    row = registry.calibration(calibration_id)
    return None if row is None else _calibration_row(row)


def calibration_history(registry, machine: str) -> pd.DataFrame:
    """One row per commissioning (oldest first): date, source, parameters, std errors."""
    table = []
    for row in registry.calibrations(machine):
        r = _calibration_row(row)
        entry = {"id": r["id"], "created_at": r["created_at"], "source": r["source"]}
        entry.update(calibration_to_dict(r["calibration"]))
        entry.update({f"{k}_se": v for k, v in r["std"].items()})
        table.append(entry)
    return pd.DataFrame(table)


def record_maintenance(
    registry,
    machine: str,
    *,
    nozzle_cleaned: bool = False,
    vial_refilled_ml: float | None = None,
    reset_theta: bool = False,
    note: str = "",
) -> dict:
    """Store a maintenance event; the next ingest applies it (:func:`apply_maintenance`)."""
    if not (nozzle_cleaned or vial_refilled_ml is not None or reset_theta):
        raise ValueError(
            "a maintenance event must name what was done: --nozzle-cleaned, "
            "--vial-refilled ML or --reset-theta"
        )
    if vial_refilled_ml is not None and not (0 < float(vial_refilled_ml) < 3.0):
        raise ValueError(f"--vial-refilled {vial_refilled_ml}: the fill must be in (0, 3) mL")
    event = {
        "nozzle_cleaned": bool(nozzle_cleaned),
        "vial_refilled_ml": None if vial_refilled_ml is None else float(vial_refilled_ml),
        "reset_theta": bool(reset_theta),
        "note": note,
    }
    created_at = registry.add_maintenance(machine, event)
    return {"created_at": created_at, **event}


def maintenance_history(registry, machine: str) -> pd.DataFrame:
    """One row per maintenance event of a machine (oldest first): when, after which print, what."""
    return pd.DataFrame(
        [
            {"id": r["id"], "created_at": r["created_at"], "after_print_seq": r["after_print_seq"]}
            | r["event"]
            for r in registry.maintenance(machine)
        ]
    )


def pending_maintenance(registry, machine: str, since_unix: float = 0.0) -> list[dict]:
    """Maintenance events done after the machine's last print (and after ``since_unix``)."""
    last = registry.latest_seq(machine) or 0
    return [r["event"] for r in registry.maintenance(machine, last, since_unix)]
