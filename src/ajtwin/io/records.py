"""Print records: one print = one 1 Hz table of inputs, outputs and (optional) truth.

A :class:`PrintRecord` holds

* ``data`` — a pandas DataFrame sampled at 1 Hz with the columns of
  :data:`INPUT_COLUMNS` and :data:`OUTPUT_COLUMNS` (display units, SPEC §3) after
  ``time_s``, optionally the truth columns :data:`TRUTH_COLUMNS` of a virtual print.
  NaN means "no measurement at this second" and is kept as such.
* ``meta`` — a dict with at least ``machine_id``, ``scenario``, ``seed``,
  ``platen_speed_mm_s``, ``units`` and the fault information ``fault_kind`` /
  ``fault_onset_s`` (``"none"`` / ``None`` for a clean print).

:func:`read_record` reads Parquet (metadata in the schema metadata under the key
``ajtwin``) or CSV (metadata as ``# meta: {json}`` comment lines at the top; a bare
CSV with only the columns is valid and gets :data:`DEFAULT_META`). Messy logs are
handled in the open: column aliases (``aliases.toml``), NaN kept, irregular time
stamps resampled to 1 s with a warning; a wrong unit scale, non-monotonic time, a
missing required column or a non-numeric cell is rejected with an error naming the
file, row and column. The schema is documented in ``docs/record_format.md``.

Examples
--------
>>> import numpy as np, pandas as pd
>>> t = np.arange(3.0)
>>> df = pd.DataFrame({"time_s": t, "atomizer_current_mA": 375.0, "carrier_flow_sccm": 23.0,
...                    "sheath_flow_sccm": 50.0, "carrier_pressure_Pa": 5661.0,
...                    "sheath_pressure_Pa": 5641.0, "linewidth_um": 43.0,
...                    "overspray_um": 29.0, "material_flow_mL_s": 1.5e-8})
>>> rec = PrintRecord(df, {})
>>> rec.inputs.shape, rec.meta["platen_speed_mm_s"]
((3, 3), 1.0)
"""

from __future__ import annotations

import copy
import csv
import json
import math
import tomllib
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.io.files import InputFileError, check_regular_file, read_toml_file

#: Version 2 adds the job columns (:data:`JOB_COLUMNS`, :data:`LINE_TRUTH_COLUMNS`) and the
#: ``job``/``camera`` metadata; version-1 records still read (:func:`read_record`).
FORMAT_VERSION = 2
PARQUET_META_KEY = b"ajtwin"
CSV_META_PREFIX = "# meta: "

TIME_COLUMN = "time_s"
INPUT_COLUMNS = ("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm")
OUTPUT_COLUMNS = (
    "linewidth_um",
    "overspray_um",
    "carrier_pressure_Pa",
    "sheath_pressure_Pa",
    "material_flow_mL_s",
)
#: Truth columns of a virtual print, in the model's state order (d_a, V_l, ΔR_T, ΔR_N, φ_A).
TRUTH_COLUMNS = (
    "true_droplet_diameter_um",
    "true_vial_volume_mL",
    "true_tube_deposition_um",
    "true_nozzle_deposition_um",
    "true_aerosol_fraction",
)
#: A job print (format version 2): the shutter and the platen speed at t_k, and for the
#: camera measurement in the row, the time its trace was printed (model reference §12).
JOB_COLUMNS = ("shutter_open", "platen_speed_mm_s", "printed_at_s")
#: The truth of the line printed at t_k (at the nozzle) of a virtual job print.
LINE_TRUTH_COLUMNS = ("true_linewidth_um", "true_overspray_um")
#: Camera modes of a job print's ``camera`` metadata.
CAMERA_MODES = ("trailing", "inspection", "at_nozzle")
#: Column order of a record's table: time, the raw log's columns, then truth.
RECORD_COLUMNS = (
    TIME_COLUMN,
    "atomizer_current_mA",
    "carrier_flow_sccm",
    "sheath_flow_sccm",
    "carrier_pressure_Pa",
    "sheath_pressure_Pa",
    "linewidth_um",
    "overspray_um",
    "material_flow_mL_s",
)
#: Columns a record must have. material_flow_mL_s may be absent (no height-profile
#: CNN on that machine): it is then added as all-NaN with a warning.
REQUIRED_COLUMNS = tuple(c for c in RECORD_COLUMNS if c != "material_flow_mL_s")
#: The alignment camera's columns: a log may lack both (a machine without a camera; they
#: are added as all-NaN with a warning), but not one of them (a camera gives both).
CAMERA_COLUMNS = ("linewidth_um", "overspray_um")

UNITS = {
    "time_s": "s",
    "atomizer_current_mA": "mA",
    "carrier_flow_sccm": "sccm",
    "sheath_flow_sccm": "sccm",
    "carrier_pressure_Pa": "Pa",
    "sheath_pressure_Pa": "Pa",
    "linewidth_um": "um",
    "overspray_um": "um",
    "material_flow_mL_s": "mL/s",
    "true_droplet_diameter_um": "um",
    "true_vial_volume_mL": "mL",
    "true_tube_deposition_um": "um",
    "true_nozzle_deposition_um": "um",
    "true_aerosol_fraction": "1",
    "shutter_open": "1",
    "platen_speed_mm_s": "mm/s",
    "printed_at_s": "s",
    "true_linewidth_um": "um",
    "true_overspray_um": "um",
}

#: Metadata a record gets when its file says nothing (e.g. a bare CSV).
DEFAULT_META = {
    "format_version": FORMAT_VERSION,
    "machine_id": "unknown",
    "scenario": "unknown",
    "seed": None,
    "platen_speed_mm_s": 1.0,
    "units": dict(UNITS),
    "fault_kind": "none",
    "fault_onset_s": None,
}

# Plausible value ranges in display units, and what a value outside them most likely
# means. Each entry: (low, high, {"too_small": hint, "too_large": hint}); a value is
# rejected when it is finite and outside [low, high]. The ranges are wide enough for
# any AJ 300-class print and narrow enough to catch a factor-of-60/1000 unit slip.
PLAUSIBLE_RANGES = {
    "atomizer_current_mA": (50.0, 1000.0, "A (expected mA; 375 mA = 0.375 A)", None),
    "carrier_flow_sccm": (
        1.0,
        200.0,
        "mL/s or L/min (expected sccm; 23 sccm = 0.383 mL/s)",
        "a unit smaller than sccm",
    ),
    "sheath_flow_sccm": (
        1.0,
        500.0,
        "mL/s or L/min (expected sccm; 50 sccm = 0.833 mL/s)",
        "a unit smaller than sccm",
    ),
    "carrier_pressure_Pa": (
        100.0,
        1e6,
        "kPa, bar or psi (expected Pa; 5661 Pa = 5.661 kPa)",
        "a unit smaller than Pa",
    ),
    "sheath_pressure_Pa": (
        100.0,
        1e6,
        "kPa, bar or psi (expected Pa; 5641 Pa = 5.641 kPa)",
        "a unit smaller than Pa",
    ),
    "linewidth_um": (1.0, 5000.0, "mm or m (expected µm; 43 µm = 0.043 mm)", "nm (expected µm)"),
    "overspray_um": (0.0, 5000.0, None, "nm (expected µm)"),
    "material_flow_mL_s": (
        0.0,
        1e-4,
        None,
        "a unit larger than mL/s per s, e.g. µL/s or nL/s (expected mL/s; typical 1.5e-8 mL/s)",
    ),
    "true_droplet_diameter_um": (0.1, 50.0, "m or mm (expected µm)", "nm (expected µm)"),
    "true_vial_volume_mL": (0.0, 10.0, None, "µL (expected mL)"),
    "true_tube_deposition_um": (-1000.0, 1000.0, None, "nm (expected µm)"),
    "true_nozzle_deposition_um": (-75.0, 75.0, None, "nm (expected µm)"),
    "true_aerosol_fraction": (0.0, 1.0, None, "a percentage or ppm (expected a fraction)"),
    "true_linewidth_um": (1.0, 5000.0, "mm or m (expected µm)", "nm (expected µm)"),
    "true_overspray_um": (0.0, 5000.0, None, "nm (expected µm)"),
}
# Columns with a lower bound of 0 can still reveal a unit slip through their median:
# overspray of a real line is micrometres, not 0.03 (mm).
MEDIAN_FLOORS = {"overspray_um": (0.5, "mm (expected µm; 29 µm = 0.029 mm)")}

#: Largest record file read (a week at 1 Hz is ~0.1 GB as CSV) and most rows a record may
#: hold (~116 days at 1 Hz): bounds on memory, so a wrong file can never take the RAM.
MAX_RECORD_BYTES = 4 << 30
MAX_RECORD_ROWS = 10_000_000
#: Fastest platen a record's metadata may state [mm/s]: AJ stages move ≤ ~200 mm/s.
MAX_PLATEN_SPEED_MM_S = 1000.0
#: Resampling may grow a table by at most this factor plus MAX_RESAMPLE_EXTRA_S grid
#: seconds (real logs have gaps of minutes, not a time stamp in another clock or unit).
MAX_RESAMPLE_GROWTH = 10
MAX_RESAMPLE_EXTRA_S = 6 * 3600

#: Time stamps closer than this to the 1 s grid count as regular.
TIME_TOLERANCE_S = 1e-6
#: When resampling, a grid point between two samples farther apart than this gets NaN.
MAX_INTERPOLATION_GAP_S = 5.0


class RecordError(ValueError):
    """A print record that cannot be read as it is; the message names file, row, column."""


@dataclass
class PrintRecord:
    """One print: a 1 Hz table (``data``) and its metadata (``meta``).

    Missing metadata keys are filled from :data:`DEFAULT_META` (the keys that were
    filled are listed in ``meta["assumed_defaults"]``).

    Parameters
    ----------
    data : pandas.DataFrame
        ``time_s`` and the record columns in display units; NaN = no measurement.
    meta : dict
        ``machine_id``, ``scenario``, ``seed``, ``platen_speed_mm_s`` [mm/s], ``units``,
        ``fault_kind``, ``fault_onset_s`` [s] and anything else JSON-serialisable.
    """

    data: pd.DataFrame
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        meta = dict(self.meta)
        assumed = list(meta.get("assumed_defaults", []))
        for key, value in DEFAULT_META.items():
            if key not in meta:
                meta[key] = copy.deepcopy(value)
                if key != "format_version":
                    assumed.append(key)
        if assumed:
            meta["assumed_defaults"] = sorted(set(assumed))
        self.meta = meta

    # -- convenient array views (display units) ----------------------------------
    @property
    def time_s(self) -> np.ndarray:
        """Sample times [s], shape (T,)."""
        return self.data[TIME_COLUMN].to_numpy(dtype=float)

    @property
    def inputs(self) -> np.ndarray:
        """Measured inputs u = [I_A mA, Q_c sccm, Q_s sccm], shape (T, 3)."""
        return self.data[list(INPUT_COLUMNS)].to_numpy(dtype=float)

    @property
    def outputs(self) -> np.ndarray:
        """Measured outputs y = [L_w µm, L_o µm, P_c Pa, P_s Pa, Q_m mL/s], (T, 5); NaN = none."""
        return self.data[list(OUTPUT_COLUMNS)].to_numpy(dtype=float)

    @property
    def has_truth(self) -> bool:
        return all(c in self.data.columns for c in TRUTH_COLUMNS)

    @property
    def true_states(self) -> np.ndarray | None:
        """True states x = [d_a µm, V_l mL, ΔR_T µm, ΔR_N µm, φ_A], (T, 5), or None."""
        if not self.has_truth:
            return None
        return self.data[list(TRUTH_COLUMNS)].to_numpy(dtype=float)

    @property
    def has_job(self) -> bool:
        """The record carries the job columns (a format-2 job print)."""
        return all(c in self.data.columns for c in JOB_COLUMNS)

    @property
    def shutter_open(self) -> np.ndarray:
        """Shutter state at each t_k (T,) as 0/1; all 1 (always printing) without a job."""
        if "shutter_open" in self.data.columns:
            return self.data["shutter_open"].to_numpy(dtype=float)
        return np.ones(len(self.data))

    @property
    def platen_speed(self) -> np.ndarray:
        """Platen speed ν [mm/s] at each t_k (T,); the metadata's speed without a job."""
        if "platen_speed_mm_s" in self.data.columns:
            return self.data["platen_speed_mm_s"].to_numpy(dtype=float)
        return np.full(len(self.data), float(self.meta["platen_speed_mm_s"]))

    @property
    def printed_at(self) -> np.ndarray:
        """Print time τ [s] of the trace measured in each row (T,), NaN where no camera
        measurement; without a job, the row's own time (the camera sees the line as printed)."""
        if "printed_at_s" in self.data.columns:
            return self.data["printed_at_s"].to_numpy(dtype=float)
        return _measured_at_row_time(self.data)

    @property
    def duration_s(self) -> float:
        t = self.time_s
        return float(t[-1] - t[0]) if len(t) else 0.0

    def __len__(self) -> int:
        return len(self.data)

    def window(self, start_s: float | None = None, stop_s: float | None = None) -> PrintRecord:
        """The samples with start_s <= time_s < stop_s, as a new record (same meta)."""
        t = self.data[TIME_COLUMN]
        keep = np.ones(len(t), dtype=bool)
        if start_s is not None:
            keep &= t >= start_s
        if stop_s is not None:
            keep &= t < stop_s
        return PrintRecord(self.data.loc[keep].reset_index(drop=True), copy.deepcopy(self.meta))


# --------------------------------------------------------------------------- #
# Aliases
# --------------------------------------------------------------------------- #


def load_aliases(path: str | Path | None = None) -> dict[str, str]:
    """Alias → canonical column name, from the packaged file plus an optional user file.

    Keys are lower-cased and stripped; the canonical names map to themselves.
    """
    tables = []
    with (resources.files("ajtwin.io") / "aliases.toml").open("rb") as fh:
        tables.append(tomllib.load(fh))
    if path is not None:
        tables.append(read_toml_file(Path(path), what="alias"))
    mapping: dict[str, str] = {c.lower(): c for c in UNITS}
    for table in tables:
        aliases = table.get("aliases", {})
        if not isinstance(aliases, dict):
            raise ValueError(f"alias file {path}: [aliases] must be a table")
        for canonical, names in aliases.items():
            if canonical not in UNITS:
                raise ValueError(
                    f"alias file names unknown column {canonical!r}; known: {', '.join(UNITS)}"
                )
            if not isinstance(names, list):
                raise ValueError(f"alias file {path}: aliases.{canonical} must be a list of names")
            for name in names:
                mapping[str(name).strip().lower()] = canonical
    return mapping


def _apply_aliases(df: pd.DataFrame, mapping: dict[str, str], where: str) -> pd.DataFrame:
    renamed: dict[str, str] = {}
    seen: dict[str, str] = {}
    for column in df.columns:
        canonical = mapping.get(str(column).strip().lower())
        if canonical is None:
            continue
        if canonical in seen:
            raise RecordError(
                f"{where}: columns {seen[canonical]!r} and {column!r} both mean {canonical!r}"
            )
        seen[canonical] = column
        if canonical != column:
            renamed[column] = canonical
    if renamed:
        pretty = ", ".join(f"{a!r} → {b!r}" for a, b in renamed.items())
        warnings.warn(f"{where}: renamed columns by alias: {pretty}", stacklevel=3)
    return df.rename(columns=renamed)


# --------------------------------------------------------------------------- #
# Validation
# --------------------------------------------------------------------------- #


def _row_label(df: pd.DataFrame, position: int, row_offset: int) -> str:
    """Row for messages: data row (1 = first data row) and, for text files, the file line."""
    label = f"row {position + 1}"
    if row_offset:
        label += f" (line {position + 1 + row_offset})"
    return label


def _as_text(series: pd.Series, where: str, column) -> pd.Series:
    """A column as stripped text; bytes that are not UTF-8 (a binary column) are refused."""
    try:
        return series.astype("string").str.strip()
    except (TypeError, ValueError, UnicodeDecodeError) as exc:
        raise RecordError(
            f"{where}: column {column!r} holds values that are not text or numbers "
            f"({type(exc).__name__}: {str(exc)[:80]})"
        ) from None


def _to_numeric(df: pd.DataFrame, where: str, row_offset: int) -> pd.DataFrame:
    out = {}
    for column in df.columns:
        series = df[column]
        if pd.api.types.is_bool_dtype(series) or pd.api.types.is_complex_dtype(series):
            # True/False or a+bj is no measurement, though NumPy would turn it into a number
            raise RecordError(
                f"{where}: column {column!r} has type {series.dtype}; expected real numbers"
            )
        if pd.api.types.is_numeric_dtype(series):
            out[column] = series.astype(float)
            continue
        # empty strings / "nan" / "NA" are missing values; anything else must be a number
        text = _as_text(series, where, column)
        blank = text.isna() | text.str.lower().isin(["", "nan", "na", "n/a", "none", "null"])
        numbers = pd.to_numeric(text.where(~blank), errors="coerce")
        bad = numbers.isna() & ~blank
        if bad.any():
            position = int(np.flatnonzero(bad.to_numpy())[0])
            raise RecordError(
                f"{where}: {_row_label(df, position, row_offset)}, column {column!r}: "
                f"value {series.iloc[position]!r} is not a number"
            )
        out[column] = numbers.astype(float)
    return pd.DataFrame(out, index=df.index)


def _check_columns(df: pd.DataFrame, where: str) -> pd.DataFrame:
    if not any(c in df.columns for c in CAMERA_COLUMNS):
        # a machine without an alignment camera: both line columns absent is a valid log
        warnings.warn(
            f"{where}: no {' or '.join(map(repr, CAMERA_COLUMNS))} column (no camera); added "
            "as all-NaN — the twin starts droplet size and aerosol fraction from priors",
            stacklevel=3,
        )
        df = df.assign(**{c: np.nan for c in CAMERA_COLUMNS})
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise RecordError(
            f"{where}: missing required column(s) {', '.join(map(repr, missing))}; "
            f"found {', '.join(map(repr, map(str, df.columns)))}. If your log names them "
            "differently, add the names to an alias file (see docs/record_format.md)."
        )
    if "material_flow_mL_s" not in df.columns:
        warnings.warn(
            f"{where}: no 'material_flow_mL_s' column; added as all-NaN (no measurement)",
            stacklevel=3,
        )
        df = df.assign(material_flow_mL_s=np.nan)
    present_truth = [c for c in TRUTH_COLUMNS if c in df.columns]
    if present_truth and len(present_truth) != len(TRUTH_COLUMNS):
        lacking = [c for c in TRUTH_COLUMNS if c not in df.columns]
        warnings.warn(f"{where}: partial truth; lacking {', '.join(lacking)}", stacklevel=3)
    return df


def _check_ranges(df: pd.DataFrame, where: str, row_offset: int) -> None:
    for column, (low, high, small_hint, large_hint) in PLAUSIBLE_RANGES.items():
        if column not in df.columns:
            continue
        values = df[column].to_numpy(dtype=float)
        if np.isinf(values).any():
            position = int(np.flatnonzero(np.isinf(values))[0])
            raise RecordError(
                f"{where}: {_row_label(df, position, row_offset)}, column {column!r}: "
                f"value {values[position]!r} is infinite (use NaN for a missing measurement)"
            )
        finite = np.isfinite(values)
        for mask, hint, side in (
            (finite & (values < low), small_hint, "below"),
            (finite & (values > high), large_hint, "above"),
        ):
            if mask.any():
                position = int(np.flatnonzero(mask)[0])
                unit = UNITS[column]
                guess = f"; the values look like {hint}" if hint else ""
                raise RecordError(
                    f"{where}: {_row_label(df, position, row_offset)}, column {column!r}: "
                    f"value {values[position]:g} is {side} the plausible range "
                    f"[{low:g}, {high:g}] {unit}{guess}"
                )
        if column in MEDIAN_FLOORS and finite.any():
            floor, hint = MEDIAN_FLOORS[column]
            if np.median(values[finite]) < floor:
                position = int(np.flatnonzero(finite & (values < floor))[0])
                raise RecordError(
                    f"{where}: {_row_label(df, position, row_offset)}, column {column!r}: "
                    f"median {np.median(values[finite]):g} {UNITS[column]} is below {floor:g}; "
                    f"the values look like {hint}"
                )


def _check_time(df: pd.DataFrame, where: str, row_offset: int) -> np.ndarray:
    t = df[TIME_COLUMN].to_numpy(dtype=float)
    if len(t) == 0:
        raise RecordError(f"{where}: the record has no rows")
    missing = ~np.isfinite(t)
    if missing.any():
        position = int(np.flatnonzero(missing)[0])
        raise RecordError(
            f"{where}: {_row_label(df, position, row_offset)}, column 'time_s': "
            f"time stamp {float(t[position])} is missing; every row needs a time"
        )
    steps = np.diff(t)
    bad = steps <= 0
    if bad.any():
        position = int(np.flatnonzero(bad)[0]) + 1
        raise RecordError(
            f"{where}: {_row_label(df, position, row_offset)}, column 'time_s': time "
            f"{t[position]:g} s does not increase (previous row {t[position - 1]:g} s); "
            "time must be strictly increasing"
        )
    if len(steps) >= 3 and np.median(steps) >= 100.0:
        raise RecordError(
            f"{where}: column 'time_s': median step {np.median(steps):g} between rows; the "
            "time looks like milliseconds (expected seconds, one row per ~1 s)"
        )
    return t


def _datetimes_to_seconds(df: pd.DataFrame, where: str) -> pd.DataFrame:
    """Wall-clock time stamps (ISO text or datetime dtype) → seconds since the first row."""
    column = df[TIME_COLUMN]
    if pd.api.types.is_numeric_dtype(column):
        return df
    if pd.api.types.is_datetime64_any_dtype(column):
        stamps = column
    else:
        text = _as_text(column, where, TIME_COLUMN)
        if pd.to_numeric(text, errors="coerce").notna().all():
            return df  # numbers stored as text; _to_numeric handles them
        # a zone (Z or ±hh:mm) on some stamps and not on others is ambiguous: refuse
        zoned = text.str.contains(r"(?:Z|[+-]\d\d:?\d\d)$", regex=True).fillna(False)
        if zoned.any() and not zoned.all():
            with_zone = int(np.flatnonzero(zoned.to_numpy())[0])
            without = int(np.flatnonzero(~zoned.to_numpy())[0])
            raise RecordError(
                f"{where}: column 'time_s': row {with_zone + 1} has a time zone and row "
                f"{without + 1} has none; give every time stamp the same zone (or none)"
            )
        try:
            stamps = pd.to_datetime(text, errors="coerce", format="ISO8601", utc=bool(zoned.any()))
        except (ValueError, TypeError, OverflowError):
            return df  # not dates pandas can read: let _to_numeric name the offending row
        if stamps.isna().any():
            return df  # not all dates: let _to_numeric name the offending row
    seconds = (stamps - stamps.iloc[0]).dt.total_seconds()
    warnings.warn(
        f"{where}: 'time_s' holds wall-clock time stamps; converted to seconds since "
        f"{stamps.iloc[0]}",
        stacklevel=3,
    )
    return df.assign(**{TIME_COLUMN: seconds.to_numpy(dtype=float)})


def _check_resample_size(t: np.ndarray, where: str, df: pd.DataFrame, row_offset: int) -> None:
    """Refuse a time column whose 1 s grid would be far larger than the table.

    One time stamp in another clock or unit (epoch seconds, 1e300) would otherwise make
    the resampler allocate a grid of billions of seconds; name the row of the largest jump.
    """
    n_grid = math.floor(t[-1] + TIME_TOLERANCE_S) - math.ceil(t[0] - TIME_TOLERANCE_S) + 1
    limit = MAX_RESAMPLE_GROWTH * len(t) + MAX_RESAMPLE_EXTRA_S
    if n_grid <= limit:
        return
    steps = np.diff(t)
    position = int(np.argmax(steps)) + 1
    raise RecordError(
        f"{where}: {_row_label(df, position, row_offset)}, column 'time_s': time stamp "
        f"{t[position]:.6g} s jumps {steps[position - 1]:.6g} s after the previous row "
        f"({t[position - 1]:.6g} s; median step {np.median(steps):.3g} s): a 1 s grid over "
        f"{n_grid:.3g} s from {len(t)} rows is refused; is that row in another clock or unit?"
    )


def resample_to_seconds(
    df: pd.DataFrame, max_gap_s: float = MAX_INTERPOLATION_GAP_S
) -> tuple[pd.DataFrame, dict]:
    """Resample a strictly increasing, irregular table onto a 1 s grid.

    Each grid second gets the linear interpolation of its two neighbouring samples;
    when either neighbour is NaN, or the two are more than ``max_gap_s`` apart, the
    grid value is NaN (no measurement), never invented.

    Returns
    -------
    (DataFrame, dict)
        The resampled table and a summary (``n_in``, ``n_out``, ``n_gap_nan``).
    """
    t = df[TIME_COLUMN].to_numpy(dtype=float)
    grid = np.arange(math.ceil(t[0] - TIME_TOLERANCE_S), math.floor(t[-1] + TIME_TOLERANCE_S) + 1)
    grid = grid.astype(float)
    right = np.clip(np.searchsorted(t, grid, side="left"), 0, len(t) - 1)
    exact = np.abs(t[right] - grid) <= TIME_TOLERANCE_S
    left = np.clip(right - 1, 0, len(t) - 1)
    left = np.where(exact, right, left)
    span = t[right] - t[left]
    weight = np.where(span > 0, (grid - t[left]) / np.where(span > 0, span, 1.0), 0.0)
    too_far = span > max_gap_s
    out = {TIME_COLUMN: grid}
    for column in df.columns:
        if column == TIME_COLUMN:
            continue
        v = df[column].to_numpy(dtype=float)
        value = v[left] + weight * (v[right] - v[left])
        value[too_far] = np.nan
        out[column] = value
    summary = {"n_in": int(len(t)), "n_out": int(len(grid)), "n_gap_nan": int(too_far.sum())}
    return pd.DataFrame(out), summary


def validate_table(
    df: pd.DataFrame,
    where: str = "<table>",
    aliases: str | Path | None = None,
    row_offset: int = 0,
) -> pd.DataFrame:
    """Check, rename and regularise a raw table into record columns (see :func:`read_record`).

    Returns a DataFrame on a 1 s grid: ``time_s``, the record columns, truth columns
    when present, then any extra columns of the log (kept, never dropped).
    """
    df = _apply_aliases(df, load_aliases(aliases), where)
    df = _check_columns(df, where)
    df = _datetimes_to_seconds(df, where)
    df = _to_numeric(df, where, row_offset)
    t = _check_time(df, where, row_offset)
    _check_ranges(df, where, row_offset)
    steps = np.diff(t)
    on_grid = len(t) == 1 or (
        np.all(np.abs(steps - 1.0) <= TIME_TOLERANCE_S)
        and abs(t[0] - round(t[0])) <= TIME_TOLERANCE_S
    )
    if not on_grid:
        _check_resample_size(t, where, df, row_offset)
        df, summary = resample_to_seconds(df.reset_index(drop=True))
        warnings.warn(
            f"{where}: irregular time stamps (steps {steps.min():g}–{steps.max():g} s); "
            f"resampled {summary['n_in']} samples to {summary['n_out']} at 1 s "
            f"(linear interpolation; {summary['n_gap_nan']} grid points in gaps > "
            f"{MAX_INTERPOLATION_GAP_S:g} s set to NaN)",
            stacklevel=2,
        )
    missing_inputs = {c: int(df[c].isna().sum()) for c in INPUT_COLUMNS if df[c].isna().any()}
    if missing_inputs:
        counts = ", ".join(f"{c}: {n}" for c, n in missing_inputs.items())
        warnings.warn(
            f"{where}: inputs missing (NaN) in some seconds ({counts}); the model needs inputs "
            "every second — fill them (e.g. hold the last set-point) before estimating",
            stacklevel=2,
        )
    order = (*RECORD_COLUMNS, *JOB_COLUMNS, *TRUTH_COLUMNS, *LINE_TRUTH_COLUMNS)
    known = [c for c in order if c in df.columns]
    extra = [c for c in df.columns if c not in known]
    return df[known + extra].reset_index(drop=True)


# --------------------------------------------------------------------------- #
# Reading and writing
# --------------------------------------------------------------------------- #


def _json_safe(meta: dict) -> dict:
    def convert(value):
        if isinstance(value, dict):
            return {str(k): convert(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [convert(v) for v in value]
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, Path):
            return str(value)
        if isinstance(value, float) and not math.isfinite(value):
            return None
        return value

    return convert(meta)


def _sniff_text(path: Path, head: bytes) -> None:
    """Refuse a file that is plainly not UTF-8 CSV text, saying what it looks like."""
    if head.startswith(b"PAR1"):
        raise RecordError(f"{path}: this is a Parquet file with a .csv name; rename it to .parquet")
    half = max(len(head) // 2, 1)
    utf16 = (
        head.startswith((b"\xff\xfe", b"\xfe\xff"))
        or max(head[0::2].count(0), head[1::2].count(0)) > 0.6 * half
    )
    if utf16:
        raise RecordError(
            f"{path}: the text is UTF-16 encoded; save the CSV as UTF-8 (e.g. Excel's "
            "'CSV UTF-8') and read it again"
        )
    if b"\x00" in head:
        line = head[: head.index(b"\x00")].count(b"\n") + 1
        raise RecordError(f"{path}: line {line}: binary data (a NUL byte), not a CSV text file")


def _csv_structure(path: Path, size: int) -> tuple[dict, int, list[str], int, bool]:
    """Metadata, header lines, column names, data-row count and whether the last row is cut.

    One streaming pass with the ``csv`` module (never the whole file in memory). Every
    data line must have as many fields as the header: a short line in the middle is an
    error naming the line; a short last line without a line end is a write that was cut
    off (the logger died mid-line) and is dropped with a warning naming the line.
    """
    meta: dict = {}
    header_lines = 0
    line_number = 0
    with path.open("rb") as raw:
        _sniff_text(path, raw.read(4096))
        if size:
            raw.seek(size - 1)
            ends_with_newline = raw.read(1) in (b"\n", b"\r")
        else:
            ends_with_newline = True
    try:
        with path.open("r", encoding="utf-8-sig", newline="") as fh:
            for line in fh:
                line_number += 1
                if not line.startswith("#"):
                    break
                header_lines += 1
                if line.startswith(CSV_META_PREFIX):
                    try:
                        value = json.loads(line[len(CSV_META_PREFIX) :])
                    except (json.JSONDecodeError, RecursionError) as exc:
                        raise RecordError(
                            f"{path}: line {header_lines}: metadata is not valid JSON "
                            f"(or nested too deeply): {str(exc)[:120]}"
                        ) from None
                    if not isinstance(value, dict):
                        raise RecordError(
                            f"{path}: line {header_lines}: metadata must be a JSON object "
                            f'{{"key": value, ...}}, got {type(value).__name__} {value!r:.60}'
                        )
                    meta.update(value)
            else:
                raise RecordError(f"{path}: no table after the header")
            header_line = header_lines + 1
            columns = next(csv.reader([line]), [])
            n_fields = len(columns)
            reader = csv.reader(fh)
            rows = 0
            last_short = None
            for fields in reader:
                if not fields:
                    continue  # blank line; pandas skips it too
                line_number = header_line + reader.line_num
                rows += 1
                if len(fields) != n_fields:
                    if last_short is not None:
                        break
                    last_short = (line_number, len(fields))
                    continue
                if last_short is not None:
                    break
            else:
                line_number = None
            if last_short is not None:
                where, count = last_short
                is_last = line_number is None
                if not (is_last and not ends_with_newline and count < n_fields):
                    raise RecordError(
                        f"{path}: line {where} has {count} fields but the header (line "
                        f"{header_line}) has {n_fields}; a cut, merged or shifted line"
                    )
                warnings.warn(
                    f"{path}: line {where} (the last) has {count} of {n_fields} fields and no "
                    "line end: the file was cut while being written; that row is dropped",
                    stacklevel=4,
                )
                rows -= 1
    except UnicodeDecodeError:
        line, byte = _first_non_utf8(path)
        raise RecordError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{byte:02x}); save the CSV as UTF-8"
        ) from None
    except csv.Error as exc:
        raise RecordError(f"{path}: line {line_number + 1}: not a valid CSV line: {exc}") from None
    _check_duplicate_names(columns, str(path))
    if not ends_with_newline and (last_short is None):
        warnings.warn(
            f"{path}: the file does not end with a line end; if it was cut while being "
            "written, the last value of the last row may be incomplete",
            stacklevel=4,
        )
    return meta, header_lines, columns, rows, not ends_with_newline


def _first_non_utf8(path: Path) -> tuple[int, int]:
    """File line (from 1) and value of the first byte that is not valid UTF-8."""
    import codecs

    decoder = codecs.getincrementaldecoder("utf-8")()
    lines = 1
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 16):
            try:
                decoder.decode(chunk)
            except UnicodeDecodeError as exc:
                # the decoder may hold up to 3 bytes of the previous chunk: count only ours
                start = max(exc.start - (len(exc.object) - len(chunk)), 0)
                return lines + chunk[:start].count(b"\n"), chunk[start]
            lines += chunk.count(b"\n")
    return lines, 0


def _check_duplicate_names(columns, where: str) -> None:
    """Two columns with the same name: refuse, naming both (never rename one silently)."""
    seen: dict[str, int] = {}
    for number, name in enumerate(columns, start=1):
        key = str(name).strip()
        if key in seen:
            raise RecordError(
                f"{where}: columns {seen[key]} and {number} are both named {key!r}; "
                "rename or remove one"
            )
        seen[key] = number


def _read_csv(path: Path) -> tuple[pd.DataFrame, dict, int]:
    size = check_regular_file(path, "print record", MAX_RECORD_BYTES)
    meta, header_lines, columns, rows, _ = _csv_structure(path, size)
    if rows > MAX_RECORD_ROWS:
        raise RecordError(f"{path}: {rows} rows is more than a record may hold ({MAX_RECORD_ROWS})")
    try:
        df = pd.read_csv(
            path,
            skiprows=header_lines,
            nrows=rows,
            encoding="utf-8-sig",
            index_col=False,
        )
    except pd.errors.EmptyDataError:
        raise RecordError(f"{path}: no table after the header") from None
    except (pd.errors.ParserError, ValueError) as exc:
        raise RecordError(f"{path}: not a valid CSV table: {exc}") from None
    # file line of data row 1 = comment lines + the column-name line + 1
    return df, meta, header_lines + 1


def _read_parquet(path: Path) -> tuple[pd.DataFrame, dict]:
    import pyarrow.parquet as pq

    check_regular_file(path, "print record", MAX_RECORD_BYTES)
    try:
        parquet = pq.ParquetFile(path)
        n_rows = parquet.metadata.num_rows
        if n_rows > MAX_RECORD_ROWS:
            raise RecordError(
                f"{path}: {n_rows} rows is more than a record may hold ({MAX_RECORD_ROWS})"
            )
        _check_duplicate_names(parquet.schema_arrow.names, str(path))
        table = parquet.read()
    except RecordError:
        raise
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise RecordError(f"{path}: not a readable Parquet file: {exc}") from None
    raw = (table.schema.metadata or {}).get(PARQUET_META_KEY)
    meta = {}
    if raw:
        try:
            meta = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise RecordError(
                f"{path}: the 'ajtwin' metadata in the Parquet schema is not valid JSON: {exc}"
            ) from None
        if not isinstance(meta, dict):
            raise RecordError(
                f"{path}: the 'ajtwin' metadata in the Parquet schema must be a JSON object, "
                f"got {type(meta).__name__} {meta!r:.60}"
            )
    try:
        df = table.to_pandas()
    except Exception as exc:  # e.g. a column type pandas cannot hold
        raise RecordError(f"{path}: columns cannot be read as a table: {exc}") from None
    for column in df.columns:
        if not (
            pd.api.types.is_numeric_dtype(df[column])
            or pd.api.types.is_datetime64_any_dtype(df[column])
            or pd.api.types.is_string_dtype(df[column])
            or df[column].dtype == object
        ):
            raise RecordError(
                f"{path}: column {column!r} has type {df[column].dtype}; expected numbers"
            )
    return df, meta


def validate_meta(meta, where: str = "<record>") -> dict:
    """Check a record's metadata: types and ranges of the keys ajtwin uses.

    ``platen_speed_mm_s`` a number in (0, :data:`MAX_PLATEN_SPEED_MM_S`], ``seed`` an integer
    or null, ``fault_onset_s`` a number ≥ 0 or null, ``machine_id``/``scenario``/``fault_kind``
    text, ``units`` an object of column → unit text. Other keys are kept as they are.

    Raises
    ------
    RecordError
        Naming ``where`` and the key.
    """
    if not isinstance(meta, dict):
        raise RecordError(f"{where}: metadata must be a JSON object, got {type(meta).__name__}")

    def bad(key, expected):
        return RecordError(f"{where}: metadata {key!r} = {meta[key]!r:.60}: expected {expected}")

    def is_number(value):
        return isinstance(value, int | float) and not isinstance(value, bool)

    if "platen_speed_mm_s" in meta:
        speed = meta["platen_speed_mm_s"]
        if not (is_number(speed) and math.isfinite(speed) and 0 < speed <= MAX_PLATEN_SPEED_MM_S):
            raise bad("platen_speed_mm_s", f"a number in (0, {MAX_PLATEN_SPEED_MM_S:g}] mm/s")
    if meta.get("seed") is not None and not (
        isinstance(meta["seed"], int) and not isinstance(meta["seed"], bool)
    ):
        raise bad("seed", "an integer or null")
    onset = meta.get("fault_onset_s")
    if onset is not None and not (is_number(onset) and math.isfinite(onset) and onset >= 0):
        raise bad("fault_onset_s", "a number of seconds ≥ 0, or null for a clean print")
    for key in ("machine_id", "scenario", "fault_kind"):
        if key in meta and not isinstance(meta[key], str):
            raise bad(key, "text")
    if "format_version" in meta and not (
        isinstance(meta["format_version"], int)
        and not isinstance(meta["format_version"], bool)
        and 1 <= meta["format_version"] <= FORMAT_VERSION
    ):
        raise bad("format_version", f"an integer 1..{FORMAT_VERSION} (this ajtwin's format)")
    _check_job_meta(meta, where)
    if "units" in meta:
        units = meta["units"]
        if not isinstance(units, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in units.items()
        ):
            raise bad("units", 'an object of column → unit text, e.g. {"linewidth_um": "um"}')
        for column, unit in units.items():
            if column in UNITS and unit not in (
                UNITS[column],
                "µm" if UNITS[column] == "um" else UNITS[column],
            ):
                raise RecordError(
                    f"{where}: column {column!r} declared in unit {unit!r}; "
                    f"records use {UNITS[column]!r} — convert before writing"
                )
    return meta


def read_record(path: str | Path, aliases: str | Path | None = None) -> PrintRecord:
    """Read a print record from Parquet (``.parquet``/``.pq``) or CSV (``.csv``).

    Parameters
    ----------
    path : str or Path
        The record file.
    aliases : str or Path, optional
        A TOML alias file (same form as ``ajtwin/io/aliases.toml``) adding column names.

    Returns
    -------
    PrintRecord
        Data on a 1 s grid in display units; NaN = no measurement.

    Raises
    ------
    RecordError
        Missing required column, non-monotonic time, a non-numeric cell, or a value
        whose scale betrays a wrong unit — the message names file, row and column
        (rows count data rows from 1, after any ``#`` header lines).
    FileNotFoundError
        When the file does not exist.

    Warns
    -----
    UserWarning
        Columns renamed by alias, irregular time stamps resampled, material flow absent.

    Examples
    --------
    >>> rec = read_record("print.parquet")          # doctest: +SKIP
    >>> rec.meta["scenario"], rec.inputs.shape      # doctest: +SKIP
    ('exp1', (5400, 3))
    """
    path = Path(path)
    try:
        check_regular_file(path, "print record", MAX_RECORD_BYTES)
    except InputFileError as exc:
        raise RecordError(str(exc)) from None
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        df, meta = _read_parquet(path)
        row_offset = 0
    elif suffix == ".csv":
        df, meta, row_offset = _read_csv(path)
    else:
        raise RecordError(f"{path}: unknown record format {suffix!r}; use .parquet or .csv")
    meta = validate_meta(dict(meta), str(path))
    data = validate_table(df, str(path), aliases=aliases, row_offset=row_offset)
    data = job_columns(data, meta, str(path), row_offset)
    meta["source_file"] = str(path)
    return PrintRecord(data, meta)


def write_record(record: PrintRecord, path: str | Path) -> Path:
    """Write a record to Parquet or CSV by suffix (metadata included, see module doc).

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    meta = _json_safe({k: v for k, v in record.meta.items() if k != "source_file"})
    meta.setdefault("units", dict(UNITS))
    meta["format_version"] = FORMAT_VERSION
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix in (".parquet", ".pq"):
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(record.data, preserve_index=False)
        schema_meta = dict(table.schema.metadata or {})
        schema_meta[PARQUET_META_KEY] = json.dumps(meta).encode()
        pq.write_table(table.replace_schema_metadata(schema_meta), path)
    elif suffix == ".csv":
        with path.open("w", encoding="utf-8", newline="") as fh:
            fh.write(f"# ajtwin print record, format {FORMAT_VERSION} (docs/record_format.md)\n")
            fh.write(CSV_META_PREFIX + json.dumps(meta) + "\n")
            record.data.to_csv(fh, index=False)
    else:
        raise ValueError(f"{path}: unknown record format {suffix!r}; use .parquet or .csv")
    return path


# --------------------------------------------------------------------------- #
# Job columns (format version 2)
# --------------------------------------------------------------------------- #


def _measured_at_row_time(data: pd.DataFrame) -> np.ndarray:
    """printed_at_s of a record without a job: the row's time where the camera measured."""
    measured = np.zeros(len(data), dtype=bool)
    for column in CAMERA_COLUMNS:
        if column in data.columns:
            measured |= np.isfinite(data[column].to_numpy(dtype=float))
    return np.where(measured, data[TIME_COLUMN].to_numpy(dtype=float), np.nan)


def job_columns(data: pd.DataFrame, meta: dict, where: str, row_offset: int = 0) -> pd.DataFrame:
    """Check a table's job columns, or add them to a version-1 record.

    A version-1 record (``meta["format_version"]`` < 2) has no job: it gets
    ``shutter_open`` = 1, ``platen_speed_mm_s`` = the metadata's platen speed and
    ``printed_at_s`` = ``time_s`` where the camera measured (NaN elsewhere). A job column
    present is checked: the shutter 0/1 (values between, from resampling an irregular log,
    are rounded with a warning), the speed in [0, MAX_PLATEN_SPEED_MM_S] mm/s, a print
    time no later than its row, and every camera measurement with its print time.
    """
    if int(meta.get("format_version", FORMAT_VERSION)) < 2:
        defaults = {
            "shutter_open": np.ones(len(data)),
            "platen_speed_mm_s": np.full(
                len(data), float(meta.get("platen_speed_mm_s", DEFAULT_META["platen_speed_mm_s"]))
            ),
            "printed_at_s": _measured_at_row_time(data),
        }
        data = data.assign(**{c: v for c, v in defaults.items() if c not in data.columns})
        order = (*RECORD_COLUMNS, *JOB_COLUMNS, *TRUTH_COLUMNS, *LINE_TRUTH_COLUMNS)
        known = [c for c in order if c in data.columns]
        return data[known + [c for c in data.columns if c not in known]]

    def refuse(bad, column, text):
        """Refuse the first row where ``bad``; ``text(position)`` says why."""
        if bad.any():
            position = int(np.flatnonzero(bad)[0])
            raise RecordError(
                f"{where}: {_row_label(data, position, row_offset)}, column {column!r}: "
                f"{text(position)}"
            )

    if "shutter_open" in data.columns:
        shutter = data["shutter_open"].to_numpy(dtype=float)
        refuse(
            ~np.isfinite(shutter) | (shutter < 0) | (shutter > 1),
            "shutter_open",
            lambda i: f"value {shutter[i]:g} is not 0 (closed) or 1 (open)",
        )
        between = (shutter != 0) & (shutter != 1)
        if between.any():
            warnings.warn(
                f"{where}: 'shutter_open' holds {int(between.sum())} values between 0 and 1 "
                "(a resampled log); rounded (0.5 and above: open)",
                stacklevel=3,
            )
            data = data.assign(shutter_open=np.floor(shutter + 0.5))
    if "platen_speed_mm_s" in data.columns:
        speed = data["platen_speed_mm_s"].to_numpy(dtype=float)
        refuse(
            ~np.isfinite(speed) | (speed < 0) | (speed > MAX_PLATEN_SPEED_MM_S),
            "platen_speed_mm_s",
            lambda i: f"value {speed[i]:g} is not a speed in [0, {MAX_PLATEN_SPEED_MM_S:g}] mm/s",
        )
    if "printed_at_s" in data.columns:
        printed = data["printed_at_s"].to_numpy(dtype=float)
        t = data[TIME_COLUMN].to_numpy(dtype=float)
        refuse(
            np.isinf(printed),
            "printed_at_s",
            lambda i: "value is infinite (use NaN for no measurement)",
        )
        refuse(
            np.isfinite(printed) & (printed > t + TIME_TOLERANCE_S),
            "printed_at_s",
            lambda i: (
                f"print time {printed[i]:g} s is after the row's time {t[i]:g} s "
                "(a camera sees only what is already printed)"
            ),
        )
        refuse(
            np.isfinite(_measured_at_row_time(data)) & ~np.isfinite(printed),
            "printed_at_s",
            lambda i: (
                "a camera measurement (linewidth_um/overspray_um) without the print "
                "time of its trace"
            ),
        )
    return data


def _check_job_meta(meta: dict, where: str) -> None:
    """The ``job`` and ``camera`` metadata of a job print (format version 2)."""

    def bad(key, expected):
        return RecordError(f"{where}: metadata {key!r} = {meta[key]!r:.80}: expected {expected}")

    if "camera" in meta:
        camera = meta["camera"]
        if not isinstance(camera, dict) or camera.get("mode") not in CAMERA_MODES:
            raise bad("camera", f'an object with "mode" one of {", ".join(CAMERA_MODES)}')
        offset = camera.get("offset_mm", [0.0, 0.0])
        if not (
            isinstance(offset, list)
            and len(offset) == 2
            and all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                for v in offset
            )
        ):
            raise bad("camera", '"offset_mm" as [dx, dy] in mm')
    if "job" in meta:
        job = meta["job"]
        if not isinstance(job, dict):
            raise bad("job", "an object (program, sha256, speeds, speed_source, repeat_to_s)")
        for key in ("process_speed_mm_s", "rapid_speed_mm_s", "repeat_to_s"):
            value = job.get(key)
            if value is not None and not (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
                and value >= 0
            ):
                raise bad("job", f'"{key}" a number >= 0 or null')
