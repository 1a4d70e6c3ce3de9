"""Print records: one print = one 1 Hz table of inputs, outputs and (optional) truth.

A :class:`PrintRecord` holds

* ``data`` — a pandas DataFrame sampled at 1 Hz with the columns of
  :data:`INPUT_COLUMNS` and :data:`OUTPUT_COLUMNS` (display units, model reference §3) after
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
file, row and column. The schema is documented in ``docs/reference/record-format.md``.
:func:`open_record` reads the same way but keeps the table in a temporary file
(:class:`SpooledRecord`: a piece of rows at a time, for a pass over a long print that must
not hold it); :func:`read_record` is it, loaded.

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

import codecs
import copy
import csv
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.config import InputFileError, check_regular_file
from ajtwin.io import spool
from ajtwin.io.columns import name_tables
from ajtwin.io.dialect import SNIFF_LINES, CsvDialect, dialect_from_name, sniff_dialect
from ajtwin.io.schema import (  # noqa: F401 (re-exported: the format's names live in schema)
    CAMERA_COLUMNS,
    CAMERA_MODES,
    CHUNK_ROWS,
    CSV_META_PREFIX,
    DEFAULT_META,
    FORMAT_VERSION,
    INPUT_COLUMNS,
    JOB_COLUMNS,
    LINE_TRUTH_COLUMNS,
    MAX_GAP_S,
    MAX_PLATEN_SPEED_MM_S,
    MAX_RECORD_BYTES,
    MAX_RECORD_ROWS,
    MAX_RECORD_SECONDS,
    OUTPUT_COLUMNS,
    PARQUET_META_KEY,
    PLAUSIBLE_RANGES,
    RECORD_COLUMNS,
    REQUIRED_COLUMNS,
    SAMPLES_COLUMN,
    SCALE_FLOORS,
    TIME_COLUMN,
    TIME_TOLERANCE_S,
    TRUTH_COLUMNS,
    UNITS,
    RecordError,
)
from ajtwin.io.spool import SpooledTable
from ajtwin.io.table import TableBuilder

#: The page that documents the format (named in every CSV a record is written to).
RECORD_FORMAT_PAGE = "docs/reference/record-format.md"


def with_defaults(meta: dict) -> dict:
    """A record's metadata with the keys it lacks filled from :data:`DEFAULT_META` (those
    filled listed in ``assumed_defaults``)."""
    meta = dict(meta)
    assumed = list(meta.get("assumed_defaults", []))
    for key, value in DEFAULT_META.items():
        if key not in meta:
            meta[key] = copy.deepcopy(value)
            if key != "format_version":
                assumed.append(key)
    if assumed:
        meta["assumed_defaults"] = sorted(set(assumed))
    return meta


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
        self.meta = with_defaults(self.meta)

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
        """Whether the record carries the true states (a virtual print)."""
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
        """Time from the first to the last sample [s]."""
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
# Aliases and tables
# --------------------------------------------------------------------------- #


def load_aliases(path: str | Path | None = None) -> dict[str, str]:
    """Alias → canonical column name, from the packaged file plus an optional user file.

    Keys are normalised as column names are matched (:func:`ajtwin.io.columns.normalise_name`);
    the canonical names map to themselves. Names that carry a unit (``Carrier Flow
    [sccm]``) are resolved by :func:`ajtwin.io.columns.resolve_columns`.
    """
    whole, _ = name_tables(path)
    return whole


def _warn(notes: list[str], stacklevel: int = 3) -> None:
    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=stacklevel)


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


def _sniff_csv(path: Path) -> tuple[CsvDialect, int]:
    """The dialect of a delimited text file from its first lines (after ``#`` lines), and
    the number of lines it was judged on (:func:`ajtwin.io.dialect.sniff_dialect`)."""
    lines: list[str] = []
    try:
        with path.open("r", encoding="utf-8-sig", newline="") as fh:
            for line in fh:
                if not lines and line.startswith("#"):
                    continue
                lines.append(line)
                if len(lines) > SNIFF_LINES:
                    break
    except UnicodeDecodeError:
        return CsvDialect(), 0  # the structure pass names the byte
    if lines and not lines[-1].endswith(("\n", "\r")):
        lines = lines[:-1]  # may be cut mid-line
    text = [line.rstrip("\r\n") for line in lines]
    return sniff_dialect(text), max(len(text) - 1, 0)


def _csv_structure(
    path: Path, size: int, dialect: CsvDialect
) -> tuple[dict, int, list[str], int, bool]:
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
            columns = next(csv.reader([line], delimiter=dialect.delimiter), [])
            n_fields = len(columns)
            reader = csv.reader(fh, delimiter=dialect.delimiter)
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


def _read_csv(
    path: Path, aliases=None, dialect: CsvDialect | None = None
) -> tuple[SpooledTable, dict, list[str]]:
    """A delimited text file → (record table on disk, metadata, notes), read in chunks."""
    size = check_regular_file(path, "print record", MAX_RECORD_BYTES)
    if dialect is None:
        with path.open("rb") as raw:
            _sniff_text(path, raw.read(4096))
        dialect, judged = _sniff_csv(path)
        if not dialect.is_default or dialect.assumed:
            assumed = "; ".join(dialect.assumed)
            # said at once: if the assumption was wrong, the error that follows is its effect
            _warn(
                [
                    f"{path}: read as {dialect.describe()} (detected from the first {judged} "
                    f"lines{'; ' + assumed if assumed else ''}); --csv-dialect sets it"
                ],
                stacklevel=5,
            )
    meta, header_lines, columns, rows, _ = _csv_structure(path, size, dialect)
    if rows > MAX_RECORD_ROWS:
        raise RecordError(f"{path}: {rows} rows is more than a record may hold ({MAX_RECORD_ROWS})")
    # file line of data row 1 = comment lines + the column-name line + 1
    names = [name if name != "" else f"Unnamed: {i}" for i, name in enumerate(columns)]
    builder = TableBuilder(
        names, str(path), aliases=aliases, dialect=dialect, line_offset=header_lines + 1
    )
    try:
        chunks = pd.read_csv(
            path,
            sep=dialect.delimiter,
            decimal=dialect.decimal,
            skiprows=header_lines,
            nrows=rows,
            encoding="utf-8-sig",
            index_col=False,
            chunksize=CHUNK_ROWS,
        )
        done = 0
        with chunks:
            for chunk in chunks:
                if chunk.shape[1] != len(names):
                    raise RecordError(
                        f"{path}: the table has {chunk.shape[1]} columns where the header "
                        f"names {len(names)}"
                    )
                builder.push(chunk, done)
                done += len(chunk)
    except pd.errors.EmptyDataError:
        raise RecordError(f"{path}: no table after the header") from None
    except pd.errors.ParserError as exc:
        raise RecordError(f"{path}: not a valid CSV table: {exc}") from None
    table = builder.finish()
    return table, meta, builder.notes


def _parquet_meta(path: Path, schema) -> dict:
    raw = (schema.metadata or {}).get(PARQUET_META_KEY)
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
    return meta


#: Rows of a Parquet record decoded at a time: Arrow holds a batch's pages and its own
#: copy of them while the table takes it (batches of 200,000 rows raised a 7-day print's
#: read by ~85 MB more than these).
PARQUET_BATCH_ROWS = 16_384


def _read_parquet(path: Path, aliases=None) -> tuple[SpooledTable, dict, list[str]]:
    """A Parquet file → (record table on disk, metadata, notes), read in row batches."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    check_regular_file(path, "print record", MAX_RECORD_BYTES)
    try:
        parquet = pq.ParquetFile(path, buffer_size=1 << 20, pre_buffer=False)
        n_rows = parquet.metadata.num_rows
        if n_rows > MAX_RECORD_ROWS:
            raise RecordError(
                f"{path}: {n_rows} rows is more than a record may hold ({MAX_RECORD_ROWS})"
            )
        names = parquet.schema_arrow.names
        _check_duplicate_names(names, str(path))
        schema = parquet.schema_arrow
    except RecordError:
        raise
    except Exception as exc:  # pyarrow raises several types for a corrupt file
        raise RecordError(f"{path}: not a readable Parquet file: {exc}") from None
    meta = _parquet_meta(path, schema)
    builder = TableBuilder(names, str(path), aliases=aliases)
    done = 0
    batches = parquet.iter_batches(batch_size=PARQUET_BATCH_ROWS)
    while True:
        try:
            batch = next(batches, None)
            if batch is None:
                break
            df = pa.Table.from_batches([batch]).to_pandas()
        except RecordError:
            raise
        except Exception as exc:  # a corrupt page, or a column type pandas cannot hold
            raise RecordError(f"{path}: not a readable Parquet file: {exc}") from None
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
        builder.push(df, done)
        done += len(df)
    # Arrow's allocator keeps the freed batches for reuse: a 24-h print's read left ~60 MB
    # held (for a 10-MB record) under everything the twin does next; the reader and its
    # batch iterator hold buffers of their own until they go (a 7-day print: ~70 MB more)
    df = batches = parquet = None
    pa.default_memory_pool().release_unused()
    if not done:
        raise RecordError(f"{path}: the record has no rows")
    table = builder.finish()
    return table, meta, builder.notes


def validate_meta(meta, where: str = "<record>") -> dict:
    """Check a record's metadata: types and ranges of the keys ajtwin uses.

    ``platen_speed_mm_s`` a number in (0, :data:`MAX_PLATEN_SPEED_MM_S`], ``seed`` an integer
    or null, ``fault_onset_s`` a number ≥ 0 or null, ``atomizer_switched_on_s`` a number or
    null, ``machine_id``/``scenario``/``fault_kind`` text, ``units`` an object of column →
    unit text. Other keys are kept as they are.

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
    switched_on = meta.get("atomizer_switched_on_s")
    if switched_on is not None and not (is_number(switched_on) and math.isfinite(switched_on)):
        raise bad("atomizer_switched_on_s", "a number of seconds, or null (not switched on)")
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


#: Suffixes read as delimited text (the dialect is detected, or given).
TEXT_SUFFIXES = (".csv", ".tsv")


def read_record(
    path: str | Path,
    aliases: str | Path | None = None,
    dialect: str | CsvDialect | None = None,
) -> PrintRecord:
    """Read a print record from Parquet (``.parquet``/``.pq``) or delimited text
    (``.csv``, ``.tsv``).

    Parameters
    ----------
    path : str or Path
        The record file.
    aliases : str or Path, optional
        A TOML alias file (same form as ``ajtwin/io/aliases.toml``) adding column names.
    dialect : str or CsvDialect, optional
        The text file's dialect: a name of :data:`ajtwin.io.dialect.DIALECTS`
        (``"semicolon-decimal-comma"``, ``"tab"``, …); None or ``"auto"``: detected.

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
        The dialect detected, columns renamed or converted, time converted, samples
        averaged per second, columns treated as missing, inputs held through a gap.

    Examples
    --------
    >>> rec = read_record("print.parquet")
    >>> rec.meta["scenario"], rec.inputs.shape      # a 2-min print
    ('exp1', (120, 3))
    """
    with open_record(path, aliases, dialect, _stacklevel=4) as source:
        return source.load()


def open_record(
    path: str | Path,
    aliases: str | Path | None = None,
    dialect: str | CsvDialect | None = None,
    *,
    _stacklevel: int = 3,
) -> SpooledRecord:
    """Read a print record as :func:`read_record` does, its table kept on disk.

    What a pass over a long print uses (``ajtwin ingest``): memory does not grow with the
    print. The same checks, notes and errors as :func:`read_record`, which is this and
    :meth:`SpooledRecord.load`. Close it (or use it in a ``with``) to let its file go.
    """
    path = Path(path)
    try:
        check_regular_file(path, "print record", MAX_RECORD_BYTES)
        chosen = dialect_from_name(dialect)
    except InputFileError as exc:
        raise RecordError(str(exc)) from None
    except ValueError as exc:
        raise RecordError(f"{path}: {exc}") from None
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        table, meta, notes = _read_parquet(path, aliases)
    elif suffix in TEXT_SUFFIXES:
        table, meta, notes = _read_csv(path, aliases, chosen)
    else:
        raise RecordError(f"{path}: unknown record format {suffix!r}; use .parquet, .csv or .tsv")
    try:
        meta = validate_meta(dict(meta), str(path))
    except BaseException:
        table.close()
        raise
    _warn(notes, stacklevel=_stacklevel)
    meta["source_file"] = str(path)
    record = SpooledRecord(table, meta)
    try:
        rounded = record.check_job_columns()
    except BaseException:
        record.close()
        raise
    if rounded:
        _warn([_rounded_shutter(str(path), rounded)], stacklevel=_stacklevel)
    return record


class SecondsAxis:
    """The times of a 1 Hz grid of ``n`` consecutive seconds from ``start_s``, as a read-only
    sequence (``len``, ``axis[k]``) that holds nothing per step."""

    def __init__(self, start_s: float, n: int):
        self.start_s, self.n = float(start_s), int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k: int) -> float:
        k = int(k)
        if k < 0:
            k += self.n
        if not 0 <= k < self.n:
            raise IndexError(f"second {k} of {self.n}")
        return self.start_s + k


class SpooledRecord:
    """A print record read from a file, its table held on disk (:func:`open_record`).

    Gives the print a piece at a time (:meth:`piece`: the rows of :meth:`load`'s record,
    as a PrintRecord of their own), one numeric column whole (:meth:`column`), or the
    whole record (:meth:`load`).

    Parameters
    ----------
    table : SpooledTable
    meta : dict
        Checked metadata (:func:`validate_meta`), with ``source_file``.
    """

    def __init__(self, table: SpooledTable, meta: dict):
        self.table = table
        self.meta = with_defaults(meta)
        self.where = str(meta.get("source_file", "<record>"))
        # a 1 Hz grid of consecutive seconds: row k is at start_s + k
        self.start_s = float(table.spool.read(0, 1)[0, 0])
        self._columns: list[str] | None = None

    def __len__(self) -> int:
        return len(self.table)

    def __enter__(self) -> SpooledRecord:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Let the table's file go."""
        self.table.close()

    def check_job_columns(self) -> int:
        """Check a format-2 record's job columns over the whole table a block at a time
        (:func:`job_rows`; errors name the row); how many shutter values were rounded."""
        version = int(self.meta.get("format_version", FORMAT_VERSION))
        if version < 2 or not any(c in self.table.columns for c in JOB_COLUMNS):
            return 0
        rounded = 0
        for start in range(0, len(self), spool.SPOOL_BLOCK_ROWS):
            stop = start + spool.SPOOL_BLOCK_ROWS
            rounded += job_rows(self.table.frame(start, stop), self.meta, self.where, start)[1]
        return rounded

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample [s]."""
        return float(len(self) - 1)

    @property
    def time_s(self) -> SecondsAxis:
        """Sample times [s] (T,), as a sequence computed on demand (not held)."""
        return SecondsAxis(self.start_s, len(self))

    @property
    def has_job(self) -> bool:
        """:meth:`load`'s record carries the job columns (:attr:`PrintRecord.has_job`)."""
        return all(c in self.columns for c in JOB_COLUMNS)

    def column(self, name: str) -> np.ndarray:
        """A numeric column of the table over the whole print (n,) (before :func:`job_columns`:
        the record's own columns)."""
        return self.table.column(name)

    def piece(self, start: int, stop: int) -> PrintRecord:
        """Rows [start, stop) of :meth:`load`'s record, as a record of their own (same meta)."""
        data, _ = job_rows(self.table.frame(start, stop), self.meta, self.where, start)
        return PrintRecord(data, self.meta)

    @property
    def columns(self) -> list[str]:
        """The columns of :meth:`load`'s record, in order."""
        if self._columns is None:
            self._columns = list(self.piece(0, min(2, len(self))).data.columns)
        return self._columns

    def column_pieces(self, name: str, rows: int | None = None):
        """A column of :meth:`load`'s record as float64 (text that is no number: NaN), a
        block of rows (:data:`~ajtwin.io.spool.SPOOL_BLOCK_ROWS`) at a time (what
        :func:`ajtwin.store.registry.record_hash` reads)."""
        rows = rows or spool.SPOOL_BLOCK_ROWS
        for start in range(0, len(self), rows):
            values = self.piece(start, start + rows).data[name]
            yield pd.to_numeric(values, errors="coerce").to_numpy(dtype=np.float64)

    def load(self) -> PrintRecord:
        """The whole record in memory (its job columns as :func:`job_columns` gives them;
        checked, and a rounding said, when it was opened)."""
        data, _ = job_rows(self.table.frame(), self.meta, self.where)
        return PrintRecord(data, dict(self.meta))


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
            fh.write(f"# ajtwin print record, format {FORMAT_VERSION} ({RECORD_FORMAT_PAGE})\n")
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


def job_columns(data: pd.DataFrame, meta: dict, where: str) -> pd.DataFrame:
    """Check a table's job columns, or add them to a version-1 record.

    A version-1 record (``meta["format_version"]`` < 2) has no job: it gets
    ``shutter_open`` = 1, ``platen_speed_mm_s`` = the metadata's platen speed and
    ``printed_at_s`` = ``time_s`` where the camera measured (NaN elsewhere). A job column
    present is checked: the shutter 0/1 (values between, from resampling an irregular log,
    are rounded with a warning), the speed in [0, MAX_PLATEN_SPEED_MM_S] mm/s, a print
    time no later than its row, and every camera measurement with its print time.
    """
    data, rounded = job_rows(data, meta, where)
    if rounded:
        warnings.warn(_rounded_shutter(where, rounded), stacklevel=3)
    return data


def _rounded_shutter(where: str, n: int) -> str:
    return (
        f"{where}: 'shutter_open' holds {n} values between 0 and 1 (a resampled log); rounded "
        "(0.5 and above: open)"
    )


def job_rows(
    data: pd.DataFrame, meta: dict, where: str, first_row: int = 0
) -> tuple[pd.DataFrame, int]:
    """:func:`job_columns` over rows of a table from its row ``first_row`` on (errors name
    the table's row); (the rows, how many shutter values between 0 and 1 were rounded)."""
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
        return data[known + [c for c in data.columns if c not in known]], 0

    def refuse(bad, column, text):
        """Refuse the first row where ``bad``; ``text(position)`` says why."""
        if bad.any():
            position = int(np.flatnonzero(bad)[0])
            raise RecordError(
                f"{where}: row {first_row + position + 1} (t = "
                f"{data[TIME_COLUMN].iloc[position]:g} s), column {column!r}: {text(position)}"
            )

    rounded = 0
    if "shutter_open" in data.columns:
        shutter = data["shutter_open"].to_numpy(dtype=float)
        refuse(
            ~np.isfinite(shutter) | (shutter < 0) | (shutter > 1),
            "shutter_open",
            lambda i: f"value {shutter[i]:g} is not 0 (closed) or 1 (open)",
        )
        between = (shutter != 0) & (shutter != 1)
        if between.any():
            rounded = int(between.sum())
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
    return data, rounded


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
