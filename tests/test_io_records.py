"""Print records: round trips, bare CSV, aliases, NaN, resampling, clear errors."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from ajtwin.io import (
    DEFAULT_META,
    RECORD_COLUMNS,
    TRUTH_COLUMNS,
    PrintRecord,
    RecordError,
    read_record,
    write_record,
)


def make_table(n=20, start=0.0, step=1.0, seed=0):
    rng = np.random.default_rng(seed)
    t = start + step * np.arange(n)
    return pd.DataFrame(
        {
            "time_s": t,
            "atomizer_current_mA": 375 + rng.normal(0, 1, n),
            "carrier_flow_sccm": 23 + rng.normal(0, 0.1, n),
            "sheath_flow_sccm": 50 + rng.normal(0, 0.1, n),
            "carrier_pressure_Pa": 5661 + rng.normal(0, 3, n),
            "sheath_pressure_Pa": 5641 + rng.normal(0, 3, n),
            "linewidth_um": 43 * np.exp(rng.normal(0, 0.04, n)),
            "overspray_um": 29 * np.exp(rng.normal(0, 0.08, n)),
            "material_flow_mL_s": 1.54e-8 * np.exp(rng.normal(0, 0.15, n)),
        }
    )


def make_record(truth=True, n=20):
    df = make_table(n)
    if truth:
        df["true_droplet_diameter_um"] = np.linspace(3.5, 3.6, n)
        df["true_vial_volume_mL"] = np.linspace(1.0, 0.999, n)
        df["true_tube_deposition_um"] = np.linspace(0, 1e-4, n)
        df["true_nozzle_deposition_um"] = np.linspace(0.03, 0.031, n)
        df["true_aerosol_fraction"] = 4.6e-7
    meta = {
        "machine_id": "aj-7",
        "scenario": "unit",
        "seed": 11,
        "platen_speed_mm_s": 2.0,
        "fault_kind": "nozzle_clog",
        "fault_onset_s": 10.0,
        "nested": {"a": [1, 2.5]},
    }
    return PrintRecord(df, meta)


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_round_trip_is_exact(tmp_path, suffix):
    record = make_record()
    record.data.loc[3, "linewidth_um"] = np.nan
    path = write_record(record, tmp_path / f"print{suffix}")
    back = read_record(path)
    pd.testing.assert_frame_equal(back.data, record.data, check_exact=True)
    for key in (
        "machine_id",
        "scenario",
        "seed",
        "platen_speed_mm_s",
        "fault_kind",
        "fault_onset_s",
        "nested",
        "units",
    ):
        assert back.meta[key] == record.meta[key], key
    assert back.meta["source_file"] == str(path)
    assert back.has_truth and back.true_states.shape == (20, 5)
    assert np.isnan(back.outputs[3, 0])


def test_bare_csv_gets_stated_defaults(tmp_path):
    path = tmp_path / "bare.csv"
    make_table(5).to_csv(path, index=False)
    record = read_record(path)
    for key in ("machine_id", "scenario", "seed", "platen_speed_mm_s", "fault_kind"):
        assert record.meta[key] == DEFAULT_META[key]
    assert record.meta["platen_speed_mm_s"] == 1.0
    assert "platen_speed_mm_s" in record.meta["assumed_defaults"]
    assert not record.has_truth and record.true_states is None
    assert list(record.data.columns) == list(RECORD_COLUMNS)


def test_aliases_packaged_and_user_file(tmp_path):
    df = make_table(5).rename(
        columns={
            "time_s": "Time (s)",
            "carrier_flow_sccm": "Q_c",
            "sheath_flow_sccm": " sheath_flow ",
            "linewidth_um": "LINEWIDTH",
            "overspray_um": "my_overspray",
        }
    )
    path = tmp_path / "log.csv"
    df.to_csv(path, index=False)
    # without the user alias the overspray column is unknown → missing required column
    with pytest.raises(RecordError, match="overspray_um"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read_record(path)
    aliases = tmp_path / "aliases.toml"
    aliases.write_text('[aliases]\noverspray_um = ["my_overspray"]\n')
    with pytest.warns(UserWarning, match="renamed columns by alias"):
        record = read_record(path, aliases=aliases)
    assert record.data["carrier_flow_sccm"].iloc[2] == pytest.approx(df["Q_c"].iloc[2])
    assert record.data["overspray_um"].iloc[4] == pytest.approx(df["my_overspray"].iloc[4])


def test_two_columns_meaning_the_same_is_an_error(tmp_path):
    df = make_table(3)
    df["Q_c"] = df["carrier_flow_sccm"]
    path = tmp_path / "dup.csv"
    df.to_csv(path, index=False)
    with pytest.raises(RecordError, match="both mean 'carrier_flow_sccm'"):
        read_record(path)


def test_nan_samples_are_kept(tmp_path):
    path = tmp_path / "gaps.csv"
    text = make_table(6).to_csv(index=False).splitlines()
    # blank out linewidth in data row 2 and pressure in row 4 (CSV empty cells, "NaN")
    header = text[0].split(",")
    row2 = text[2].split(",")
    row2[header.index("linewidth_um")] = ""
    text[2] = ",".join(row2)
    row4 = text[4].split(",")
    row4[header.index("carrier_pressure_Pa")] = "NaN"
    text[4] = ",".join(row4)
    path.write_text("\n".join(text) + "\n")
    record = read_record(path)
    assert len(record) == 6
    assert np.isnan(record.data["linewidth_um"].iloc[1])
    assert np.isnan(record.data["carrier_pressure_Pa"].iloc[3])
    assert record.data.isna().sum().sum() == 2


def test_irregular_time_is_averaged_per_second_with_warning(tmp_path):
    df = make_table(6)
    df["time_s"] = [0.0, 0.9, 1.3, 3.0, 4.5, 12.0]
    df["linewidth_um"] = [40.0, 41.0, 44.0, 45.0, 48.0, 50.0]
    path = tmp_path / "irregular.parquet"
    write_record(PrintRecord(df, {}), path)
    with pytest.warns(UserWarning) as caught:
        record = read_record(path)
    messages = " ".join(str(w.message) for w in caught)
    assert "resampled 6 samples to 13 seconds by averaging each second" in messages
    assert "without complete inputs" in messages  # the 7.5 s gap is a gap in the inputs too
    np.testing.assert_array_equal(record.time_s, np.arange(13.0))
    lw = record.data["linewidth_um"].to_numpy()
    # step k holds k − ½ ≤ t < k + ½: hand-computed means, NaN where no sample fell
    np.testing.assert_array_equal(lw, [40.0, 42.5, np.nan, 45.0, np.nan, 48.0, *[np.nan] * 6, 50.0])
    counts = record.data["samples_per_s"].to_numpy()
    np.testing.assert_array_equal(counts, [1, 2, 0, 1, 0, 1, 0, 0, 0, 0, 0, 0, 1])
    q_c = df["carrier_flow_sccm"].to_numpy()
    inputs = record.data["carrier_flow_sccm"].to_numpy()
    assert inputs[1] == pytest.approx((q_c[1] + q_c[2]) / 2)
    # seconds without a sample: inputs held at the last value (the live twin's rule)
    assert inputs[2] == inputs[1] and inputs[4] == inputs[3] and (inputs[6:12] == q_c[4]).all()


def test_missing_material_flow_is_added_as_nan_with_warning(tmp_path):
    path = tmp_path / "no_qm.csv"
    make_table(4).drop(columns="material_flow_mL_s").to_csv(path, index=False)
    with pytest.warns(UserWarning, match="material_flow_mL_s"):
        record = read_record(path)
    assert record.data["material_flow_mL_s"].isna().all()


@pytest.mark.parametrize(
    ("column", "factor", "row", "hint"),
    [
        ("carrier_flow_sccm", 1 / 60, 1, "mL/s"),  # flows in mL/s
        ("sheath_flow_sccm", 1 / 60, 1, "mL/s"),
        ("carrier_pressure_Pa", 1e-3, 1, "kPa"),  # pressures in kPa
        ("sheath_pressure_Pa", 1e-5, 1, "bar"),
        ("atomizer_current_mA", 1e-3, 1, "A "),  # current in A
        ("linewidth_um", 1e-3, 1, "mm"),  # linewidth in mm
        ("overspray_um", 1e-3, 1, "mm"),
    ],
)
def test_wrong_unit_scale_is_rejected_naming_file_row_column(tmp_path, column, factor, row, hint):
    df = make_table(8)
    df[column] *= factor
    path = tmp_path / "units.csv"
    df.to_csv(path, index=False)
    with pytest.raises(RecordError) as info:
        read_record(path)
    message = str(info.value)
    assert str(path) in message and f"row {row} " in message and repr(column) in message
    assert hint in message


def test_single_bad_value_is_located(tmp_path):
    df = make_table(8)
    df.loc[5, "carrier_pressure_Pa"] = 5.7  # one sample in kPa
    path = tmp_path / "one.csv"
    write_record(PrintRecord(df, {}), path)
    with pytest.raises(RecordError) as info:
        read_record(path)
    # data row 6; the written file has 2 comment lines and a header line before it
    assert "row 6 (line 9)" in str(info.value)
    assert "'carrier_pressure_Pa'" in str(info.value)
    assert path.read_text().splitlines()[8].split(",")[4] == "5.7"


def test_non_monotonic_time_is_rejected(tmp_path):
    df = make_table(6)
    df.loc[4, "time_s"] = 2.5
    path = tmp_path / "time.parquet"
    write_record(PrintRecord(df, {}), path)
    with pytest.raises(RecordError, match=r"row 5, column 'time_s'.*does not increase"):
        read_record(path)
    df.loc[4, "time_s"] = 3.0  # duplicate stamp
    write_record(PrintRecord(df, {}), path)
    with pytest.raises(RecordError, match="row 5"):
        read_record(path)


def test_missing_required_column_is_rejected(tmp_path):
    path = tmp_path / "missing.csv"
    make_table(4).drop(columns=["sheath_pressure_Pa"]).to_csv(path, index=False)
    with pytest.raises(RecordError, match=r"missing required column\(s\) 'sheath_pressure_Pa'"):
        read_record(path)


def test_non_numeric_cell_is_rejected(tmp_path):
    df = make_table(4).astype({"linewidth_um": object})
    df.loc[2, "linewidth_um"] = "n.a.?"
    path = tmp_path / "text.csv"
    df.to_csv(path, index=False)
    with pytest.raises(RecordError, match=r"row 3 \(line 4\), column 'linewidth_um'.*not a number"):
        read_record(path)


def test_declared_unit_mismatch_is_rejected(tmp_path):
    record = make_record()
    record.meta["units"] = {**record.meta["units"], "carrier_pressure_Pa": "kPa"}
    path = write_record(record, tmp_path / "declared.parquet")
    with pytest.raises(RecordError, match="declared in unit 'kPa'"):
        read_record(path)


def test_extra_columns_are_kept_not_dropped(tmp_path):
    df = make_table(4)
    df["stage_temperature_C"] = 60.0
    path = tmp_path / "extra.csv"
    df.to_csv(path, index=False)
    record = read_record(path)
    assert "stage_temperature_C" in record.data.columns


def test_unknown_suffix_and_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_record(tmp_path / "nope.csv")
    path = tmp_path / "x.xlsx"
    path.write_text("a")
    with pytest.raises(RecordError, match="unknown record format"):
        read_record(path)


def test_window_and_views():
    record = make_record(n=30)
    part = record.window(10, 20)
    assert len(part) == 10 and part.time_s[0] == 10 and part.meta["seed"] == 11
    assert record.inputs.shape == (30, 3) and record.outputs.shape == (30, 5)
    assert list(TRUTH_COLUMNS) == [c for c in record.data.columns if c.startswith("true_")]


def test_missing_inputs_are_held_and_warned(tmp_path):
    df = make_table(5)
    df.loc[2, "carrier_flow_sccm"] = np.nan
    path = tmp_path / "input_gap.csv"
    df.to_csv(path, index=False)
    with pytest.warns(UserWarning, match="carrier_flow_sccm: 1"):
        record = read_record(path)
    np.testing.assert_array_equal(record.inputs[2], record.inputs[1])
    assert np.isnan(record.outputs[2]).all()
    outputs = ["linewidth_um", "overspray_um", "carrier_pressure_Pa", "sheath_pressure_Pa",
               "material_flow_mL_s"]  # fmt: skip
    np.testing.assert_array_equal(record.outputs[3], df.loc[3, outputs].to_numpy(float))


def test_wall_clock_time_stamps_become_seconds(tmp_path):
    df = make_table(4)
    df["time_s"] = [
        "2026-11-21T14:00:00",
        "2026-11-21T14:00:01",
        "2026-11-21T14:00:02",
        "2026-11-21T14:00:03",
    ]
    path = tmp_path / "clock.csv"
    df.to_csv(path, index=False)
    with pytest.warns(UserWarning, match="wall-clock"):
        record = read_record(path)
    np.testing.assert_array_equal(record.time_s, [0.0, 1.0, 2.0, 3.0])


def test_time_in_milliseconds_is_rejected(tmp_path):
    df = make_table(5)
    df["time_s"] = np.arange(5) * 1000.0
    path = tmp_path / "ms.csv"
    df.to_csv(path, index=False)
    with pytest.raises(RecordError, match="milliseconds"):
        read_record(path)


def test_overspray_that_is_often_zero_but_reaches_micrometres_is_read_as_micrometres(tmp_path):
    """A line held with almost no overspray (the closed loop's own prints: 0 for half the print,
    1–3 µm otherwise; median 0.13 µm) is in µm, not refused as mm; a column of zeros is the
    quality check's (constant), not a unit."""
    df = make_table(400)
    df["overspray_um"] = np.where(np.arange(400) < 220, 0.0, 1.0 + (np.arange(400) % 7) * 0.3)
    path = tmp_path / "low.csv"
    df.to_csv(path, index=False)
    record = read_record(path)
    assert np.nanmax(record.data["overspray_um"]) == pytest.approx(2.8)
    df["overspray_um"] = 0.0
    df.to_csv(path, index=False)
    with pytest.warns(UserWarning, match="'overspray_um' treated as missing"):
        record = read_record(path)
    assert record.data["overspray_um"].isna().all()
