"""``ajtwin live --follow``: a growing record file read with the record reader's rules.

The live follower and ``read_record`` must read the same file alike — a byte-order mark,
CRLF, a European dialect, names with units, 10 Hz rows averaged per second — however the
file grows (cut anywhere, mid-line or mid-character), with the follower incremental.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS, read_record
from ajtwin.simulation import simulate

COLUMNS9 = slice(0, 9)


@pytest.fixture(scope="module")
def table():
    return simulate("exp1", seed=2, duration_min=2.0).data.iloc[:, COLUMNS9].copy()


def _quiet_read(path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_record(path, **kwargs)


def _european_instrument_log(table: pd.DataFrame) -> tuple[bytes, pd.DataFrame]:
    """';', decimal comma, '.' thousands, BOM, CRLF, names with units, kPa, 10 Hz rows;
    and the same rows in the record's units."""
    t = np.round(np.arange(0, table["time_s"].iloc[-1] + 1e-9, 0.1), 1)
    rng = np.random.default_rng(3)
    fast = {"Time [s]": t}
    names = {
        "atomizer_current_mA": "Atomizer Current [mA]",
        "carrier_flow_sccm": "Carrier Flow [sccm]",
        "sheath_flow_sccm": "Sheath Flow [sccm]",
        "carrier_pressure_Pa": "Carrier Pressure (kPa)",
        "sheath_pressure_Pa": "Sheath Pressure (kPa)",
        "linewidth_um": "Linewidth [µm]",
        "overspray_um": "Overspray [µm]",
        "material_flow_mL_s": "Material Flow [nL/s]",
    }
    for column, name in names.items():
        values = np.interp(t, table["time_s"], table[column].interpolate().bfill())
        if column == "linewidth_um":
            values = values + rng.normal(0, 1.0, len(t))
        if column.endswith("_Pa"):
            values = values / 1000.0
        if column == "material_flow_mL_s":
            values = values * 1e6
        fast[name] = values

    def cell(value):
        text = f"{value:,.6f}"
        return text.replace(",", "X").replace(".", ",").replace("X", ".")

    lines = [";".join(fast)]
    lines += [";".join(cell(v) for v in row) for row in zip(*fast.values())]
    exact = pd.DataFrame({"time_s": t})
    for column, name in names.items():
        factor = 1000.0 if column.endswith("_Pa") else 1e-6 if column.startswith("mat") else 1.0
        exact[column] = np.round(fast[name], 6) * factor  # as printed (6 decimals)
    return ("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"), exact


def _follow_in_pieces(path, data: bytes, cuts) -> list:
    from ajtwin.io.follow import CsvFollower

    follower = CsvFollower(path)
    samples, done = [], 0
    for cut in sorted(cuts) + [len(data)]:
        with path.open("ab") as fh:
            fh.write(data[done:cut])
        done = cut
        got, _ = follower.poll()
        samples += got
    samples += follower.flush()[0]
    return samples


@pytest.mark.parametrize(
    "cuts", [[], [1, 2, 3], [137, 5000, 5001, 40000], list(range(7, 90000, 6007))]
)
def test_follower_reads_a_growing_file_as_read_record_does(tmp_path, table, cuts):
    data, exact = _european_instrument_log(table)
    path = tmp_path / "growing.csv"
    samples = _follow_in_pieces(path, data, [c for c in cuts if c < len(data)])
    record = _quiet_read(path)
    assert [t for t, _, _ in samples] == list(record.time_s)
    np.testing.assert_allclose(np.array([u for _, u, _ in samples]), record.inputs, rtol=1e-12)
    np.testing.assert_allclose(
        np.array([y for _, _, y in samples]), record.outputs, rtol=1e-12, equal_nan=True
    )
    # and the file is what the twin needs: kPa → Pa, nL/s → mL/s, 10 rows per second averaged
    means = exact.groupby(np.floor(exact["time_s"] + 0.5)).mean()
    for column in ("carrier_pressure_Pa", "linewidth_um", "material_flow_mL_s"):
        np.testing.assert_allclose(record.data[column], means[column], rtol=1e-9)
    assert (record.data["samples_per_s"].to_numpy()[1:-1] == 10).all()


def test_follower_holds_back_the_first_rows_to_judge_the_columns(tmp_path, table):
    """A 3-decimal material flow (all zero) never reaches the live twin as measurements."""
    from ajtwin.io.follow import CsvFollower

    path = tmp_path / "r3.csv"
    path.write_bytes(table.to_csv(index=False, float_format="%.3f").encode())
    follower = CsvFollower(path)
    samples, log = follower.poll()
    assert len(samples) == len(table) - 1  # the last second stays open until the log ends
    assert np.isnan([y[4] for _, _, y in samples]).all()
    assert any("column 'material_flow_mL_s' treated as missing" in line for line in log)


def test_live_follow_stores_a_bom_file_as_estimate_reads_it(tmp_path, table):
    """The finding: ``live --follow`` refused a BOM ("no column(s) ['time_s']")."""
    from ajtwin.cli.live import live
    from ajtwin.store.registry import Registry

    path = tmp_path / "bom.csv"
    path.write_bytes(("\ufeff" + table.to_csv(index=False).replace("\n", "\r\n")).encode())
    store = tmp_path / "r.sqlite"
    args = ["--machine", "m1", "--follow", str(path), "--idle-timeout", "2", "--store", str(store)]
    result = CliRunner().invoke(live, args)
    assert result.exit_code == 0, result.output
    assert "print stored as registry print id" in result.output
    registry = Registry(store)
    arrays = registry.print_arrays(registry.last_print("m1")["id"])
    record = _quiet_read(path)
    np.testing.assert_array_equal(arrays["time_s"], record.time_s)
    np.testing.assert_array_equal(arrays["inputs"], record.inputs)
    np.testing.assert_array_equal(arrays["measurements"], record.outputs)


def test_live_follow_takes_the_dialect_option(tmp_path, table):
    """--csv-dialect reaches the follower: a file the detection would misread is read."""
    from ajtwin.io.follow import CsvFollower

    rows = ["time_s;" + ";".join([*INPUT_COLUMNS, *OUTPUT_COLUMNS])]
    for k in range(40):  # every number reads two ways: 5.661 (Pa? kPa?)
        rows.append(f"{k};375;23;50;{43 + k % 5};{29 + k % 7};5.{661 + k % 3};5.{641 + k % 4};")
    path = tmp_path / "ambiguous.csv"
    path.write_text("\n".join(rows) + "\n")
    samples, _ = CsvFollower(path, dialect="semicolon-decimal-comma").poll()
    assert [y[2] for _, _, y in samples[:3]] == [5661.0, 5662.0, 5663.0]
