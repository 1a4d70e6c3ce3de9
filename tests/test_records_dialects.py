"""Property: a table written in any CSV dialect reads as the same table written as Parquet.

Hypothesis draws a table (a print's columns, optionally a quoted note column), a dialect —
separator ``,`` ``;`` tab, decimal mark ``.`` or ``,``, thousands grouping, byte-order
mark, CRLF or LF, quoting — and for each column how many decimals it is printed with
(fixed or scientific). The CSV read must equal the Parquet read of the exact values
within half a unit of the last printed digit: a tolerance that depends only on the
printed precision. Where the file is genuinely ambiguous (every number could be read two
ways) the reader must say what it assumed, and the named dialect (``--csv-dialect``) must
then read it exactly.
"""

from __future__ import annotations

import csv
import io
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ajtwin.io.records import PrintRecord, read_record, write_record

_COMMON = dict(
    deadline=None,
    derandomize=False,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    database=None,
)
settings.register_profile("dialects", max_examples=80, **_COMMON)
settings.register_profile("dialects-long", max_examples=2000, **_COMMON)
PROFILES = [
    pytest.param("dialects", id="dialects"),
    pytest.param("dialects-long", id="dialects-long", marks=pytest.mark.slow),
]

#: Decimals a column may be printed with, fine enough that no column is judged too coarse
#: (io/resolution.toml): ('f', n) fixed, ('e', n) scientific. The flows have two decimals at
#: least: at one (0.1 sccm, the limit 0.15) the 12–40 values of a drawn table can all fall on
#: even tenths, and the reader then rightly sees a 0.2 sccm step and refuses the column.
PRINTED = {
    "time_s": [("f", 0), ("f", 1), ("f", 3)],
    "atomizer_current_mA": [("f", 0), ("f", 2), ("f", 6)],
    "carrier_flow_sccm": [("f", 2), ("f", 3), ("f", 6)],
    "sheath_flow_sccm": [("f", 2), ("f", 3), ("e", 6)],
    "carrier_pressure_Pa": [("f", 0), ("f", 1), ("f", 4)],
    "sheath_pressure_Pa": [("f", 0), ("f", 2), ("e", 8)],
    "linewidth_um": [("f", 1), ("f", 2), ("f", 5)],
    "overspray_um": [("f", 1), ("f", 3), ("e", 5)],
    "material_flow_mL_s": [("e", 3), ("e", 6), ("f", 11)],
}


@dataclass(frozen=True)
class CsvDialect:
    """A dialect as the test writes it (its name is the reader's ``--csv-dialect``)."""

    delimiter: str
    decimal: str

    @property
    def name(self) -> str:
        base = {",": "comma", ";": "semicolon", "\t": "tab"}[self.delimiter]
        return base + ("-decimal-comma" if self.decimal == "," else "")


def base_table(n: int, seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    return pd.DataFrame(
        {
            "time_s": np.arange(n, dtype=float),
            "atomizer_current_mA": 375 + rng.normal(0, 5, n),
            "carrier_flow_sccm": 23 + rng.normal(0, 0.3, n),
            "sheath_flow_sccm": 50 + rng.normal(0, 0.3, n),
            "carrier_pressure_Pa": 5661 + rng.normal(0, 20, n),
            "sheath_pressure_Pa": 5641 + rng.normal(0, 20, n),
            "linewidth_um": 43 * np.exp(rng.normal(0, 0.04, n)),
            "overspray_um": 29 * np.exp(rng.normal(0, 0.08, n)),
            "material_flow_mL_s": 1.54e-8 * np.exp(rng.normal(0, 0.15, n)),
        }
    )


def _format(value: float, kind: str, decimals: int, dialect: CsvDialect, group: bool) -> str:
    if kind == "e":
        text = f"{value:.{decimals}e}"
    else:
        text = f"{value:,.{decimals}f}" if group else f"{value:.{decimals}f}"
    # ',' groups and '.' marks the decimals in Python's format: swap for a comma dialect
    if dialect.decimal == ",":
        text = text.replace(",", "\0").replace(".", ",").replace("\0", ".")
    return text


def _tolerance(value: float, kind: str, decimals: int) -> float:
    """Half a unit of the last printed digit (plus float noise)."""
    if kind == "e":
        scale = 10.0 ** np.floor(np.log10(abs(value))) if value else 1.0
        return 0.5 * 10.0**-decimals * scale * (1 + 1e-9) + 1e-300
    return 0.5 * 10.0**-decimals * (1 + 1e-9) + 1e-12 * abs(value)


@st.composite
def exports(draw):
    n = draw(st.integers(12, 40))
    table = base_table(n, draw(st.integers(0, 2**16)))
    dialect = CsvDialect(draw(st.sampled_from([",", ";", "\t"])), draw(st.sampled_from(".,")))
    # thousands grouping: never with a ',' separator and a '.' decimal (',' would split)
    group = draw(st.booleans()) and not (dialect.delimiter == "," and dialect.decimal == ".")
    formats = {c: draw(st.sampled_from(PRINTED[c])) for c in table.columns}
    note = draw(st.booleans())
    return {
        "table": table,
        "dialect": dialect,
        "group": group,
        "formats": formats,
        "note": note,
        "bom": draw(st.booleans()),
        "crlf": draw(st.booleans()),
        "quoting": draw(st.sampled_from([csv.QUOTE_MINIMAL, csv.QUOTE_ALL])),
    }


def write_export(case, path) -> pd.DataFrame:
    """The CSV text of ``case``; returns the tolerance of every cell (same shape)."""
    table, dialect = case["table"], case["dialect"]
    tolerance = pd.DataFrame(index=table.index)
    cells = {}
    for column in table.columns:
        kind, decimals = case["formats"][column]
        cells[column] = [_format(v, kind, decimals, dialect, case["group"]) for v in table[column]]
        tolerance[column] = [_tolerance(v, kind, decimals) for v in table[column]]
    if case["note"]:
        cells["Operator note"] = [
            'wiped; nozzle, "left"' if k == 3 else ("" if k % 2 else "ok")
            for k in range(len(table))
        ]
    buffer = io.StringIO()
    writer = csv.writer(
        buffer,
        delimiter=dialect.delimiter,
        quoting=case["quoting"],
        lineterminator="\r\n" if case["crlf"] else "\n",
    )
    writer.writerow(list(cells))
    writer.writerows(zip(*cells.values()))
    text = ("\ufeff" if case["bom"] else "") + buffer.getvalue()
    path.write_bytes(text.encode("utf-8"))
    return tolerance


def _read_quietly(path, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        record = read_record(path, **kwargs)
    return record, [str(w.message) for w in caught]


def _matches(record, reference, tolerance) -> bool:
    for column in tolerance.columns:
        got = record.data[column].to_numpy(float)
        want = reference.data[column].to_numpy(float)
        if got.shape != want.shape or not np.all(np.abs(got - want) <= tolerance[column]):
            return False
    return True


@pytest.mark.parametrize("profile", PROFILES)
def test_csv_in_any_dialect_reads_as_the_parquet_table(profile, tmp_path):
    @settings(settings.get_profile(profile))
    @given(case=exports())
    def run(case):
        parquet = write_record(PrintRecord(case["table"], {}), tmp_path / "exact.parquet")
        reference = read_record(parquet)
        path = tmp_path / "export.csv"
        tolerance = write_export(case, path)
        record, said = _read_quietly(path)
        if not _matches(record, reference, tolerance):
            # only a file that can be read two ways may differ, and the reader must say so
            assert any("assumed" in s for s in said), (case["dialect"], said)
            record, _ = _read_quietly(path, dialect=case["dialect"].name)
            assert _matches(record, reference, tolerance), case["dialect"]
        if case["note"]:
            assert record.data["Operator note"][3] == 'wiped; nozzle, "left"'
        assert len(record) == len(reference)

    run()


def test_the_comparison_bites(tmp_path):
    """A reader off by more than the printed precision is caught (the tolerance is not
    loose): the same export, one pressure cell one unit of its last digit off."""
    case = {
        "table": base_table(15, 1),
        "dialect": CsvDialect(";", ","),
        "group": True,
        "formats": {c: PRINTED[c][1] for c in PRINTED},
        "note": False,
        "bom": True,
        "crlf": True,
        "quoting": csv.QUOTE_MINIMAL,
    }
    reference = read_record(write_record(PrintRecord(case["table"], {}), tmp_path / "e.parquet"))
    path = tmp_path / "export.csv"
    tolerance = write_export(case, path)
    record, _ = _read_quietly(path)
    assert _matches(record, reference, tolerance)
    record.data.loc[4, "carrier_pressure_Pa"] += 0.1  # one unit of the printed 0.1 Pa
    assert not _matches(record, reference, tolerance)
