"""What the dashboard reads from the machine registry — the one adapter to its schema.

Every page and the registry watcher get their data through :class:`RegistryView`, so a
change of the registry's schema (migrations, new per-machine fields) touches this module
only. Values are in model reference §3 display units (µm, mL, mA, sccm, Pa, mL/s); arrays leave as
plain lists with NaN → ``None`` (JSON has no NaN).

A machine's commissioning (active calibration ± standard errors), maintenance and the
model–machine guard's verdict on its newest print come from :func:`care_fields` (through
:mod:`ajtwin.store.calibration` and the print summary); pages show them when present.

Parameters of the view
----------------------
path : str or Path
    An existing registry file (``ajtwin machine add`` creates one).

Example
-------
>>> import os, tempfile
>>> from ajtwin.store.registry import Registry
>>> path = os.path.join(tempfile.mkdtemp(), "r.sqlite")
>>> Registry(path).add_machine("lab1")["name"]
'lab1'
>>> view = RegistryView(path)
>>> [(m["name"], m["status"]) for m in view.fleet()]
[('lab1', 'idle')]
"""

from __future__ import annotations

import threading
from pathlib import Path

import click
import numpy as np
import pandas as pd

from ajtwin import units
from ajtwin.apps.detection.batch import detect_anomalies
from ajtwin.apps.detection.causes import cause_action, cause_keys, cause_words
from ajtwin.apps.detection.mismatch import MISMATCH_CAUSE, mismatch_line
from ajtwin.apps.detection.settings import CUSUM_CHANNELS, DetectorSettings, cusum_thresholds
from ajtwin.apps.quality.live_map import part_payload
from ajtwin.engine.commissioning import aerosol_level
from ajtwin.engine.ingest import detector_inputs as stored_detector_inputs
from ajtwin.engine.print_job import load_stored_print, map_stored_print
from ajtwin.engine.start import machine_twin
from ajtwin.estimation.commission import aerosol_level_note
from ajtwin.io.records import read_record
from ajtwin.model.names import (
    INPUT_SYMBOLS,
    OUTPUT_NAMES,
    OUTPUT_SYMBOLS,
    STATE_NAMES,
    STATE_SYMBOLS,
)
from ajtwin.store import queries
from ajtwin.store.calibration import active_calibration, maintenance_history
from ajtwin.store.registry import Registry, RegistryError

#: the units a page shows the states in (φ_A, a volume fraction, in ppm by volume) ...
STATE_UNITS = ("µm", "mL", "µm", "µm", "ppm")
#: ... and the factor from the model's units (display units of model reference §3) to them
STATE_SCALE = (1.0, 1.0, 1.0, 1.0, float(units.fraction_to_ppm(1.0)))
#: the units a page shows the outputs in (Q_m in nL/s) and the factor from the model's
OUTPUT_UNITS = tuple(units.display(name).unit for name in OUTPUT_NAMES)
OUTPUT_SCALE = tuple(units.display(name).scale for name in OUTPUT_NAMES)
INPUT_UNITS = ("mA", "sccm", "sccm")
#: the hidden states shown on the fleet page, in this order: d_a, φ_A, ΔR_N, V_l
KEY_STATES = (0, 4, 3, 1)
#: points per trace sent to a page (longer prints are decimated; CUSUM/NIS keep peaks)
MAX_POINTS = 1500
SPARK_POINTS = 60
#: prints whose plot series are kept in memory (a page per viewer asks for the same print)
SERIES_CACHE = 16
#: part maps of stored prints kept in memory (each took a re-run of the twin)
PART_CACHE = 4

#: what a page says of each alarm cause: its words and the action (``{machine}`` in it is
#: the page's machine), from ``data/causes.toml``
CAUSES = {
    cause: {"words": cause_words(cause), "action": cause_action(cause, "{machine}")}
    for cause in cause_keys()
}

NAMES = {
    "states": list(STATE_SYMBOLS),
    "state_units": list(STATE_UNITS),
    "state_scale": list(STATE_SCALE),
    "outputs": list(OUTPUT_SYMBOLS),
    "output_units": list(OUTPUT_UNITS),
    "output_scale": list(OUTPUT_SCALE),
    "causes": CAUSES,
    # θ [1/s] shown as drift rates, per cent of the state per hour
    "theta_scale": float(units.drift_rate_percent_per_hour(1.0)),
    "theta_unit": units.DRIFT_RATE_UNIT,
    "inputs": list(INPUT_SYMBOLS),
    "input_units": list(INPUT_UNITS),
    "key_states": list(KEY_STATES),
}


def json_list(array, digits: int | None = None):
    """A NumPy array as nested lists, NaN/inf → None (JSON), optionally rounded."""
    a = np.asarray(array, dtype=float)
    if digits is not None:
        with np.errstate(invalid="ignore"):
            a = np.round(a, digits)
    out = a.astype(object)
    out[~np.isfinite(a)] = None
    return out.tolist()


def decimate(n: int, max_points: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most ``max_points`` evenly spaced samples of ``n``, last included.

    >>> decimate(10, 4).tolist()
    [0, 3, 6, 9]
    """
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(int))


def binned_max(values, index) -> np.ndarray:
    """Max of ``values`` (T, …) over each bin that ends at ``index[i]`` (peaks survive)."""
    values = np.asarray(values, dtype=float)
    starts = np.concatenate([[0], np.asarray(index)[:-1] + 1])
    return np.stack([np.nanmax(values[s : e + 1], axis=0) for s, e in zip(starts, index)])


#: the maintenance event that resolves a fault (a cleaned nozzle, a refilled vial)
RESOLVED_BY = {"nozzle_clog": "nozzle_cleaned", "ink_low": "vial_refilled_ml"}


def maintenance_after(registry, name: str, seq: int) -> list[dict]:
    """The machine's maintenance events recorded after its print ``seq``."""
    events = maintenance_history(registry, name)
    if events.empty:
        return []
    return events[events["after_print_seq"] >= seq].to_dict("records")


def headline_alarm(alarms: list[dict], maintenance: list[dict] = ()) -> tuple:
    """(headline, the others) of a print's alarms (in detection order).

    The headline is the first fault still unresolved: not a model–machine mismatch (not a
    fault) and not undone by maintenance since (:data:`RESOLVED_BY`); a later alarm is often
    a consequence of the first. With no such fault, the first alarm. (None, []) for none.

    >>> clog = {"cause": "nozzle_clog", "detected_s": 3600}
    >>> leak = {"cause": "carrier_leak", "detected_s": 4300}
    >>> headline_alarm([clog, leak])[0]["cause"]
    'nozzle_clog'
    >>> headline_alarm([clog, leak], [{"nozzle_cleaned": True}])[0]["cause"]
    'carrier_leak'
    """
    if not alarms:
        return None, []

    def resolved(alarm) -> bool:
        key = RESOLVED_BY.get(alarm["cause"])
        return key is not None and any(bool(m.get(key)) for m in maintenance)

    faults = [a for a in alarms if a["cause"] != MISMATCH_CAUSE and not resolved(a)]
    headline = faults[0] if faults else alarms[0]
    return headline, [a for a in alarms if a is not headline]


def care_fields(registry, name: str) -> dict:
    """Commissioning, maintenance and the model–machine guard of machine ``name``.

    Read through :mod:`ajtwin.store.calibration` and the newest print's summary (its
    ``mismatch`` entry, written at ingest by :func:`ajtwin.apps.detection.mismatch.assess_run`).
    Keys present only when there is something to show (``aerosol_level``: always):

    * ``commissioned_at`` — ISO time of the active (newest) calibration;
    * ``calibration`` — that calibration: ``id``, ``source``, ``created_at`` and
      ``parameters`` [{``name``, ``value``, ``std_error``, ``determined``}];
    * ``last_maintenance_at`` — ISO time of the newest maintenance event, and
      ``last_maintenance`` (what was done);
    * ``aerosol_level`` — always: ``note`` (how well φ_A's level is known, in words),
      ``pinned_by`` (what pinned it at commissioning; [] = nothing), ``relative_std``;
    * ``mismatch`` — when the newest print's guard fired: ``seq``, ``line`` (one short
      line in words), ``message`` (the guard's reasons in full),
      ``outputs`` and ``states`` it names, ``first_s``, ``fixes``;
      ``model_fit`` — ``{"seq", "ok"}`` whenever the newest print was checked.
    """

    out: dict = {}
    active = active_calibration(registry, name)
    # how well φ_A's level is known: pinned at commissioning, or relative to the generation
    # model only (model reference §11)
    level = None if active is None else aerosol_level(active)
    out["aerosol_level"] = {
        "note": aerosol_level_note(level),
        "pinned_by": [] if level is None else list(level.get("pinned_by", [])),
        "relative_std": None if level is None else level.get("relative_std"),
    }
    if active is not None:
        values = active["calibration"]._asdict()
        out["commissioned_at"] = active["created_at"]
        out["calibration"] = {
            "id": int(active["id"]),
            "source": active["source"],
            "created_at": active["created_at"],
            "parameters": [
                {
                    "name": key,
                    "value": float(values[key]),
                    "std_error": None
                    if active["std"].get(key) is None
                    else float(active["std"][key]),
                    "determined": bool(active["determined"].get(key, False)),
                }
                for key in values
            ],
        }
    events = maintenance_history(registry, name)
    if not events.empty:
        last = events.iloc[-1]
        out["last_maintenance_at"] = str(last["created_at"])
        done = [
            "nozzle cleaned" if last.get("nozzle_cleaned") else "",
            f"vial refilled to {last['vial_refilled_ml']:g} mL"
            if pd.notna(last.get("vial_refilled_ml"))
            else "",
            "θ reset" if last.get("reset_theta") else "",
        ]
        out["last_maintenance"] = ", ".join(d for d in done if d)
    newest = registry.last_print(name, in_chain=False)
    guard = None if newest is None else newest["summary"].get("mismatch")
    if isinstance(guard, dict):
        out["model_fit"] = {"seq": int(newest["seq"]), "ok": not guard.get("mismatch")}
        if guard.get("mismatch"):
            out["mismatch"] = {
                "seq": int(newest["seq"]),
                "line": mismatch_line(guard),
                "message": str(guard.get("message", "")),
                "outputs": list(guard.get("outputs") or []),
                "states": list(guard.get("states") or []),
                "first_s": guard.get("first_s"),
                "fixes": list(guard.get("fixes") or []),
            }
    return out


def _source_file(source: str) -> Path | None:
    path = Path(str(source).split(" + ")[0].strip())
    if path.suffix.lower() in (".parquet", ".csv") and path.is_file():
        return path
    return None


class RegistryView:
    """Read-only view of a registry for the pages (see module docstring)."""

    def __init__(self, path):
        # never creates a registry (an older one is migrated on open, as by every command)
        self.registry = Registry(path, create=False)
        self.path = self.registry.path  # an SQLite file, or a PostgreSQL location
        # one connection shared by the server's worker threads: serialise its use
        self._lock = threading.Lock()
        self._truth_cache: dict[int, np.ndarray | None] = {}
        self._series_cache: dict[tuple, dict] = {}
        self._part_cache: dict[tuple, dict] = {}

    def close(self):
        """Close the registry connection."""
        self.registry.close()

    # ------------------------------------------------------------------ changes
    def change_marker(self) -> tuple[int, int, int]:
        """(PRAGMA data_version, last print id, last machine id): changes on any commit."""
        with self._lock:
            return queries.change_marker(self.registry)

    def prints_after(self, print_id: int) -> list[dict]:
        """Prints committed with an id above ``print_id``: machine, seq, id, anomalies."""
        with self._lock:
            return queries.prints_after(self.registry, print_id)

    # ------------------------------------------------------------------ fleet
    def fleet(self) -> list[dict]:
        """One summary per machine: status, last print, last alarm, key states with trend."""
        with self._lock:
            out = []
            for listed in self.registry.machines():
                row = self.registry.machine(listed["name"])
                # the twin's current state: the last print in the chain (registry rule)
                last = self.registry.last_print(row["name"])
                latest_seq = queries.latest_seq(self.registry, row["name"])
                alarms = queries.newest_print_alarms(self.registry, row["name"])
                n_prints = row["n_prints"]
                entry = {
                    "name": row["name"],
                    "created_at": row["created_at"],
                    "notes": row.get("notes", ""),
                    "n_prints": int(n_prints),
                    "last_print": None,
                    "alarm": None,
                    "other_alarms": [],
                    "states": None,
                    "status": "idle",
                }
                if last is not None:
                    mean = last["end_mean"]
                    std = queries.reported_end_std(self.registry, last)
                    means = queries.print_array(self.registry, last["id"], "means")
                    time_s = queries.print_array(self.registry, last["id"], "time_s")
                    entry["last_print"] = {
                        "seq": int(last["seq"]),
                        "ingested_at": last["ingested_at"],
                        "duration_s": float(last["duration_s"]),
                    }
                    entry["states"] = []
                    for k in KEY_STATES:
                        trend = None
                        if means is not None and len(means) > 1:
                            idx = decimate(len(means), SPARK_POINTS)
                            t = time_s[idx] if time_s is not None else idx.astype(float)
                            trend = {"t": json_list(t), "v": json_list(means[idx, k])}
                        entry["states"].append(
                            {
                                "symbol": STATE_SYMBOLS[k],
                                "unit": STATE_UNITS[k],
                                "scale": STATE_SCALE[k],
                                "mean": float(mean[k]),
                                "std": float(std[k]),
                                "trend": trend,
                            }
                        )
                if alarms:
                    entry["alarm"], entry["other_alarms"] = headline_alarm(
                        alarms, maintenance_after(self.registry, row["name"], alarms[0]["seq"])
                    )
                    # a mismatch is not a fault: the status column says it, once
                    if entry["alarm"]["cause"] == MISMATCH_CAUSE:
                        entry["alarm"] = None
                    else:  # the cause in words and what to do about it
                        cause = entry["alarm"]["cause"]
                        entry["alarm"] = {
                            **entry["alarm"],
                            "words": cause_words(cause),
                            "action": cause_action(cause, row["name"]),
                        }
                    entry["other_alarms"] = [
                        a for a in entry["other_alarms"] if a["cause"] != MISMATCH_CAUSE
                    ]
                # the latest print raised a fault alarm (the guard's own "mismatch, not a
                # fault" events make the status mismatch below, as on the machine page)
                if queries.count_alarms(self.registry, row["name"], latest_seq, MISMATCH_CAUSE):
                    entry["status"] = "alarm"
                entry.update(care_fields(self.registry, row["name"]))
                if entry.get("mismatch") and entry["status"] != "alarm":
                    entry["status"] = "mismatch"
                out.append(entry)
        return out

    # ------------------------------------------------------------------ one machine
    def machine(self, name: str) -> dict:
        """The machine row, print history, alarms, last state ± σ and θ."""
        with self._lock:
            machine = self.registry.machine(name)
            history = self.registry.history(name)
            anomalies = self.registry.anomalies(name)
            last = self.registry.last_print(name)
            prints = []
            for rec in history.to_dict("records"):
                mean_nis = queries.print_summary(self.registry, rec["print_id"]).get("mean_nis")
                prints.append(
                    {
                        "seq": int(rec["seq"]),
                        "print_id": int(rec["print_id"]),
                        "ingested_at": rec["ingested_at"],
                        "duration_min": float(rec["duration_min"]),
                        "scenario": rec.get("scenario"),
                        "source": rec["source"],
                        "anomalies": int(rec["anomalies"]),
                        "mean_nis": mean_nis,
                        # in the chain ("ok") or kept for history only (excluded/dropped)
                        "status": rec.get("status", "ok"),
                        "status_reason": rec.get("status_reason", ""),
                        # the program the print ran ("" when stored without its job)
                        "program": rec.get("program", ""),
                    }
                )
            optional = care_fields(self.registry, machine["name"])
        out = {
            "name": machine["name"],
            "created_at": machine["created_at"],
            "notes": machine.get("notes", ""),
            "limits": machine["limits"],
            "prints": prints,
            "alarms": [
                {k: (None if v != v else v) for k, v in a.items()}
                for a in anomalies.to_dict("records")
            ],
            "last": None,
            "names": NAMES,
            **optional,
        }
        if last is not None:
            out["last"] = {
                "seq": int(last["seq"]),
                "mean": json_list(last["end_mean"]),
                "std": json_list(queries.reported_end_std(self.registry, last)),
                "theta": json_list(last["theta_after"]),
            }
        return out

    def _truth(self, print_row: dict) -> np.ndarray | None:
        """True states (T, 5) from the print's source file, when it is a virtual print."""
        pid = int(print_row["id"])
        if pid not in self._truth_cache:
            truth = None
            path = _source_file(print_row["source"])
            if path is not None:
                try:
                    record = read_record(path)
                    if record.has_truth and len(record) == int(print_row["n_samples"]):
                        truth = np.asarray(record.true_states, dtype=float)
                except (OSError, ValueError, KeyError):
                    truth = None
            self._truth_cache[pid] = truth
        return self._truth_cache[pid]

    def print_series(self, name: str, seq: int, max_points: int = MAX_POINTS) -> dict:
        """Per-second arrays of one print for the plots, decimated to ``max_points``.

        Returns time [s], states ± σ (and truth when known), measured and one-step
        predicted outputs, inputs, θ per step, the detectors (CUSUM g per channel with
        thresholds, windowed-NIS −log₁₀ p with its threshold) and the print's alarms.
        """

        key = (name, int(seq), int(max_points))
        if key in self._series_cache:  # a stored print never changes: reuse its series
            return self._series_cache[key]
        with self._lock:
            p = self.registry.print_by_seq(name, seq)
            a = self.registry.print_arrays(p["id"])
            detector_inputs = None
            needed = ("measurements", "predicted_outputs", "innovation_variances", "nis")
            if all(k in a for k in needed):
                # P_k's diagonal where only key frames of P are kept (the registry's rule)
                detector_inputs = stored_detector_inputs(self.registry, p["id"])
        t = a["time_s"]
        idx = decimate(len(t), max_points)
        out = {
            "machine": name,
            "seq": int(seq),
            "n_samples": int(len(t)),
            "time_s": json_list(t[idx]),
            "means": json_list(a["means"][idx]),
            "stds": json_list(a["stds"][idx]),
            "measured": json_list(a["measurements"][idx]) if "measurements" in a else None,
            "predicted": json_list(a["predicted_outputs"][idx])
            if "predicted_outputs" in a
            else None,
            "inputs": json_list(a["inputs"][idx]) if "inputs" in a else None,
            "theta": json_list(a["theta_per_step"][idx]) if "theta_per_step" in a else None,
            "truth": None,
            "detectors": None,
            "alarms": [],
            "names": NAMES,
        }
        truth = self._truth(p)
        if truth is not None:
            out["truth"] = json_list(truth[idx])
        if detector_inputs is not None:
            s = DetectorSettings()
            det = detect_anomalies(**detector_inputs, settings=s)
            g = np.maximum(det.cusum_pos, det.cusum_neg)
            with np.errstate(divide="ignore"):
                log_p = -np.log10(np.maximum(det.window_nis_p, 1e-300))
            out["detectors"] = {
                "channels": list(CUSUM_CHANNELS),
                "cusum": json_list(binned_max(g, idx), 3),
                "cusum_thresholds": detector_thresholds(s),
                "window_nis_log10p": json_list(binned_max(log_p, idx), 3),
                "window_nis_threshold": float(-np.log10(s.nis_alpha)),
                "window_s": s.nis_window_s,
            }
            out["alarms"] = [
                {
                    "detected_s": ev.detected_s,
                    "onset_s": ev.onset_s,
                    "cause": ev.cause,
                    "description": ev.description,
                    "detectors": ", ".join(ev.detectors),
                }
                for ev in det.events
            ]
        if len(self._series_cache) >= SERIES_CACHE:
            self._series_cache.pop(next(iter(self._series_cache)))
        self._series_cache[key] = out
        return out

    def part_map(self, name: str, seq: int, tolerance=None) -> dict:
        """The part map of a stored print as the page draws it
        (:func:`ajtwin.apps.quality.live_map.part_payload`): read under the lock, mapped (the
        twin re-run, seconds to a minute) outside it; kept for the next viewer.
        ``tolerance``: instead of the one stored with the print's job."""
        key = (name, int(seq), None if tolerance is None else tuple(tolerance))
        if key in self._part_cache:
            return self._part_cache[key]
        with self._lock:
            stored = load_stored_print(self.registry, name, int(seq))
        payload = part_payload(map_stored_print(stored, tolerance))
        if len(self._part_cache) >= PART_CACHE:
            self._part_cache.pop(next(iter(self._part_cache)))
        self._part_cache[key] = payload
        return payload

    def forecast_start(self, name: str, nominal_theta: bool = False):
        """(twin with the machine's θ, mean, cov, inputs now, limits, last seq): the start
        ``ajtwin forecast``/``advise`` use, from the same function
        (:func:`ajtwin.engine.start.machine_twin`)."""

        with self._lock:
            try:
                twin, mean, cov, u_now, machine, last = machine_twin(
                    self.registry, name, nominal_theta
                )
            except click.ClickException as exc:
                raise RegistryError(exc.message) from None
        return twin, mean, cov, np.asarray(u_now, float), machine["limits"], int(last["seq"])


def detector_thresholds(settings) -> list[float]:
    """CUSUM decision intervals h per channel (L_w, L_o, P_c, P_s, Q_m, P_c+P_s)."""
    return [float(h) for h in cusum_thresholds(settings)]


__all__ = ["RegistryView", "NAMES", "KEY_STATES", "STATE_NAMES", "json_list", "decimate"]
