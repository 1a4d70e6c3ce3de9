"""The record format's columns, units, plausible ranges and limits (shared by the readers).

See docs/reference/record-format.md; :mod:`ajtwin.io.records` re-exports these names.
"""

from __future__ import annotations

#: Version 2 adds the job columns (:data:`JOB_COLUMNS`, :data:`LINE_TRUTH_COLUMNS`) and the
#: ``job``/``camera`` metadata; version-1 records still read (:func:`ajtwin.io.read_record`).
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
#: Time stamps closer than this count as equal (a print time against its row's time) [s].
TIME_TOLERANCE_S = 1e-6
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
# Columns with a lower bound of 0 can still reveal a unit slip through their scale: overspray
# of a real line is micrometres, not 0.03 (mm). Refused when 95 % of the values are below the
# floor and some are above 0: a print whose overspray is often 0 but reaches a micrometre or
# two is in µm, and a column of zeros is the quality check's (constant: treated as missing).
SCALE_FLOORS = {"overspray_um": (0.5, "mm (expected µm; 29 µm = 0.029 mm)")}

#: Largest record file read and most rows (samples) it may hold: a CSV is read in chunks
#: of CHUNK_ROWS rows, so rows cost reading time (~1.5 s per million), not memory; 10 M
#: rows is a week of a 10 Hz log, 116 days of a 1 Hz one.
MAX_RECORD_BYTES = 4 << 30
MAX_RECORD_ROWS = 10_000_000
CHUNK_ROWS = 200_000
#: Longest print a record may span on the 1 s grid [s]: 14 days. The record's table and what
#: the twin keeps per second grow with it (the reader's table: 87 MB for 14 days; ``ajtwin
#: estimate`` on them: 3.8 GB, docs/reference/record-format.md "Limits"), so this bounds a
#: run's memory.
MAX_RECORD_SECONDS = 14 * 86400
#: Fastest platen a record's metadata may state [mm/s]: AJ stages move ≤ ~200 mm/s.
MAX_PLATEN_SPEED_MM_S = 1000.0
#: Longest gap between two rows [s]: a longer one is a clock jump or a time stamp in another
#: unit, not an outage (the live twin drops a sample this far ahead, ajtwin.estimation.samples).
MAX_GAP_S = 6 * 3600
#: Column of a resampled record: how many of the log's samples each second averages.
SAMPLES_COLUMN = "samples_per_s"


class RecordError(ValueError):
    """A print record that cannot be read as it is; the message names file, row, column."""
