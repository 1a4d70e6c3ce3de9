"""Per-machine calibrations and maintenance events in the registry (model reference §11).

Two tables of the registry (schema migration 4 of :mod:`ajtwin.store.registry`; export,
import and compact carry them like the prints):

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

import datetime as _dt
import json
import time

import numpy as np
import pandas as pd

from ajtwin.model.calibration import calibration_from_dict, calibration_to_dict
from ajtwin.store.registry import _CALIBRATION_SCHEMA

# created by the registry's schema migration 4; kept here for registries opened before it
_TABLES = _CALIBRATION_SCHEMA


def _has_tables(registry) -> bool:
    rows = registry._conn.execute(
        "SELECT name FROM sqlite_master WHERE type = 'table' AND name IN "
        "('calibrations', 'maintenance_events')"
    ).fetchall()
    return len(rows) == 2


def ensure_tables(registry) -> None:
    """Create the calibration tables if this registry does not have them (every registry
    opened by :class:`~ajtwin.store.registry.Registry` has them since schema 4; this
    covers a connection whose tables were dropped or a hand-made registry)."""
    conn = registry._conn
    if _has_tables(registry):
        return
    if conn.in_transaction:  # inside a caller's transaction: add them there
        for statement in _TABLES.split(";"):
            if statement.strip():
                conn.execute(statement)
        _add_long_run_column(conn)
        return
    conn.execute("BEGIN IMMEDIATE")
    try:
        for statement in _TABLES.split(";"):
            if statement.strip():
                conn.execute(statement)
        _add_long_run_column(conn)
    except Exception:
        conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def _add_long_run_column(conn) -> None:
    # schema 5's column on tables made here from the schema-4 statements
    columns = {r[1] for r in conn.execute("PRAGMA table_info(calibrations)").fetchall()}
    if "long_run_json" not in columns:
        conn.execute(
            "ALTER TABLE calibrations ADD COLUMN long_run_json TEXT NOT NULL DEFAULT 'null'"
        )


def _now() -> tuple[str, float]:
    now = time.time()
    return _dt.datetime.fromtimestamp(now, _dt.UTC).isoformat(timespec="seconds"), now


def _last_seq(registry, machine: str) -> int:
    # the newest print, in the chain or not: events and calibrations come after it
    last = registry.last_print(machine, in_chain=False)
    return 0 if last is None else int(last["seq"])


def save_calibration(
    registry, machine: str, result, source: str, long_run_history: dict | None = None
) -> int:
    """Store a :class:`~ajtwin.estimation.commission.CommissioningResult`; returns its id.

    ``long_run_history``: the detectors' long-run statistics on the commissioning print
    (:func:`ajtwin.engine.commissioning.commissioning_long_run_history`), carried to the next print.
    """
    ensure_tables(registry)
    machine_id = registry.machine(machine)["id"]
    created_at, unix = _now()
    cur = registry._conn.execute(
        "INSERT INTO calibrations (machine_id, created_at, created_unix, source, after_print_seq,"
        " calibration_json, std_json, prior_std_json, determined_json, priors_json, notes_json,"
        " end_mean_json, end_cov_json, calibration_cov_json, noise_factors_json, long_run_json)"
        " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (
            machine_id,
            created_at,
            unix,
            source,
            _last_seq(registry, machine),
            json.dumps(calibration_to_dict(result.calibration)),
            json.dumps(result.std),
            json.dumps(result.prior_std),
            json.dumps(result.determined),
            # φ_A's level (what pinned it) rides with the priors: no schema change
            json.dumps({**result.priors, "aerosol_level": getattr(result, "aerosol_level", {})}),
            json.dumps(result.notes),
            json.dumps(np.asarray(result.end_state, float).tolist()),
            json.dumps(np.asarray(result.end_state_cov, float).tolist()),
            json.dumps(np.asarray(result.calibration_cov, float).tolist()),
            json.dumps(
                None if result.noise_factors is None else np.asarray(result.noise_factors).tolist()
            ),
            json.dumps(long_run_history),
        ),
    )
    return int(cur.lastrowid)


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
    machine_id = registry.machine(machine)["id"]
    if not _has_tables(registry):
        return None
    row = registry._conn.execute(
        "SELECT * FROM calibrations WHERE machine_id = ? ORDER BY id DESC LIMIT 1", (machine_id,)
    ).fetchone()
    return None if row is None else _calibration_row(row)


def calibration_by_id(registry, calibration_id: int) -> dict | None:
    """The calibration row ``calibration_id`` (as :func:`active_calibration` gives it), or
    None when there is none (a print names the calibration it ran with)."""
    if not _has_tables(registry):
        return None
    row = registry._conn.execute(
        "SELECT * FROM calibrations WHERE id = ?", (int(calibration_id),)
    ).fetchone()
    return None if row is None else _calibration_row(row)


def calibration_history(registry, machine: str) -> pd.DataFrame:
    """One row per commissioning (oldest first): date, source, parameters, std errors."""
    machine_id = registry.machine(machine)["id"]
    if not _has_tables(registry):
        return pd.DataFrame()
    rows = registry._conn.execute(
        "SELECT * FROM calibrations WHERE machine_id = ? ORDER BY id", (machine_id,)
    ).fetchall()
    table = []
    for row in rows:
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
    ensure_tables(registry)
    machine_id = registry.machine(machine)["id"]
    event = {
        "nozzle_cleaned": bool(nozzle_cleaned),
        "vial_refilled_ml": None if vial_refilled_ml is None else float(vial_refilled_ml),
        "reset_theta": bool(reset_theta),
        "note": note,
    }
    created_at, unix = _now()
    registry._conn.execute(
        "INSERT INTO maintenance_events (machine_id, created_at, created_unix, after_print_seq,"
        " event_json) VALUES (?, ?, ?, ?, ?)",
        (machine_id, created_at, unix, _last_seq(registry, machine), json.dumps(event)),
    )
    return {"created_at": created_at, **event}


def maintenance_history(registry, machine: str) -> pd.DataFrame:
    """One row per maintenance event of a machine (oldest first): when, after which print, what."""
    machine_id = registry.machine(machine)["id"]
    if not _has_tables(registry):
        return pd.DataFrame()
    rows = registry._conn.execute(
        "SELECT * FROM maintenance_events WHERE machine_id = ? ORDER BY id", (machine_id,)
    ).fetchall()
    return pd.DataFrame(
        [
            {"id": r["id"], "created_at": r["created_at"], "after_print_seq": r["after_print_seq"]}
            | json.loads(r["event_json"])
            for r in rows
        ]
    )


def pending_maintenance(registry, machine: str, since_unix: float = 0.0) -> list[dict]:
    """Maintenance events done after the machine's last print (and after ``since_unix``)."""
    machine_id = registry.machine(machine)["id"]
    if not _has_tables(registry):
        return []
    rows = registry._conn.execute(
        "SELECT * FROM maintenance_events WHERE machine_id = ? AND after_print_seq = ? "
        "AND created_unix >= ? ORDER BY id",
        (machine_id, _last_seq(registry, machine), since_unix),
    ).fetchall()
    return [json.loads(r["event_json"]) for r in rows]
