"""Bad inputs get clear errors, never tracebacks or silent wrong results.

Each test reproduces one corruption of a virtual print (or one hostile file) and pins the
outcome: a clear error naming file, row and column, or a warning naming the line, never a
traceback of another type, a hang or a silently wrong record.
"""

from __future__ import annotations

import json
import os
import threading
import warnings

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.config import InputFileError, check_regular_file
from ajtwin.io.records import RecordError, read_record, write_record
from ajtwin.simulation import simulate

COLUMNS9 = slice(0, 9)


@pytest.fixture(scope="module")
def virtual_print():
    """A 3-minute virtual print (with truth)."""
    return simulate("exp1", seed=1, duration_min=3.0)


@pytest.fixture
def table(virtual_print):
    return virtual_print.data.iloc[:, COLUMNS9].copy()


def _no_hang(function, timeout_s=30.0, fifo=None):
    """Run function in a thread; fail (instead of hanging the suite) if it blocks."""
    outcome = {}

    def target():
        try:
            outcome["value"] = function()
        except BaseException as exc:  # noqa: BLE001 — handed back to the test
            outcome["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        if fifo is not None:  # release a reader blocked in open()
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail(f"{function} blocked for {timeout_s} s")
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


# --------------------------------------------------------------------------- #
# What once ended in a traceback: a clear error now
# --------------------------------------------------------------------------- #
def test_csv_metadata_that_is_not_an_object_is_refused(tmp_path, table):
    path = tmp_path / "ml.csv"
    path.write_text("# meta: [1, 2, 3]\n" + table.to_csv(index=False))
    with pytest.raises(RecordError, match=r"ml\.csv: line 1: metadata must be a JSON object"):
        read_record(path)


def test_parquet_metadata_that_is_not_an_object_is_refused(tmp_path, virtual_print):
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(virtual_print.data, preserve_index=False)
    pq.write_table(table.replace_schema_metadata({b"ajtwin": b"[1,2,3]"}), tmp_path / "ml.parquet")
    with pytest.raises(RecordError, match=r"ml\.parquet: the 'ajtwin' metadata .* JSON object"):
        read_record(tmp_path / "ml.parquet")
    pq.write_table(table.replace_schema_metadata({b"ajtwin": b"{oops"}), tmp_path / "bj.parquet")
    with pytest.raises(RecordError, match=r"bj\.parquet: .*metadata.* not valid JSON"):
        read_record(tmp_path / "bj.parquet")


def test_units_that_are_not_an_object_are_refused(tmp_path, table):
    path = tmp_path / "mu.csv"
    path.write_text('# meta: {"units": "SI"}\n' + table.to_csv(index=False))
    with pytest.raises(RecordError, match=r"mu\.csv: metadata 'units' = 'SI'"):
        read_record(path)


@pytest.mark.parametrize("stamp", [1.7e9, 2e7, 1e300])
def test_one_wild_time_stamp_is_named_not_resampled(tmp_path, table, stamp):
    """An epoch time stamp in the last row once made the resampler allocate 12.7 GiB."""
    table.loc[len(table) - 1, "time_s"] = stamp
    path = tmp_path / "epoch.csv"
    table.to_csv(path, index=False)
    last = len(table)
    with pytest.raises(RecordError, match=rf"epoch\.csv: row {last} \(line {last + 1}\), "
                                          r"column 'time_s': time stamp .* jumps"):  # fmt: skip
        read_record(path)


def test_a_real_gap_is_still_resampled(tmp_path, table):
    """A 20-minute logger pause is a gap (NaN), not a wild time stamp."""
    table.loc[len(table) // 2 :, "time_s"] += 1200.0
    path = tmp_path / "gap.csv"
    table.to_csv(path, index=False)
    with pytest.warns(UserWarning, match="resampled"):
        record = read_record(path)
    assert len(record) == len(table) + 1200
    assert np.isnan(record.outputs[len(table) // 2 + 10, 2])


def test_scenario_path_that_is_a_directory_device_or_fifo_is_refused(tmp_path):
    from ajtwin.simulation.scenarios import load_scenario

    with pytest.raises(InputFileError, match="is a directory"):
        load_scenario(tmp_path)
    if os.path.exists("/dev/zero"):
        with pytest.raises(InputFileError, match="/dev/zero: is a device"):
            load_scenario("/dev/zero")
    fifo = tmp_path / "sc.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputFileError, match="sc.toml: is a FIFO"):
        _no_hang(lambda: load_scenario(fifo), fifo=fifo)
    big = tmp_path / "big.toml"
    with big.open("wb") as fh:
        fh.truncate((1 << 20) + 1)
    with pytest.raises(InputFileError, match="larger than any scenario file"):
        load_scenario(big)


def test_hang_record_fifo_in_reader_and_cli(tmp_path):
    from ajtwin.cli.estimate import estimate

    fifo = tmp_path / "f.csv"
    os.mkfifo(fifo)
    with pytest.raises(RecordError, match="f.csv: is a FIFO"):
        _no_hang(lambda: read_record(fifo), fifo=fifo)
    result = _no_hang(
        lambda: CliRunner().invoke(estimate, [str(fifo), "--out", str(tmp_path / "s.csv")]),
        fifo=fifo,
    )
    assert result.exit_code == 1 and "is a FIFO" in result.output
    assert not isinstance(result.exception, Exception) or isinstance(result.exception, SystemExit)


def test_regular_file_check_uses_stat_only(tmp_path):
    path = tmp_path / "x.csv"
    path.write_bytes(b"abc")
    assert check_regular_file(path, "x", max_bytes=3) == 3
    with pytest.raises(InputFileError, match="limit 2 bytes"):
        check_regular_file(path, "x", max_bytes=2)
    with pytest.raises(FileNotFoundError, match="not found"):
        check_regular_file(tmp_path / "none.csv")


# --------------------------------------------------------------------------- #
# What once gave a silently wrong result: an error or a warning now
# --------------------------------------------------------------------------- #
def _cut_last_line(table, keep_fields=4, keep_chars=3) -> str:
    lines = table.to_csv(index=False).splitlines()
    cells = lines[-1].split(",")
    return "\n".join(
        lines[:-1] + [",".join(cells[:keep_fields] + [cells[keep_fields][:keep_chars]])]
    )


def test_csv_cut_mid_line_drops_the_row_and_names_the_line(tmp_path, table):
    path = tmp_path / "tr.csv"
    path.write_text(_cut_last_line(table))
    with pytest.warns(UserWarning, match=rf"line {len(table) + 1} \(the last\) has 5 of 9 fields"):
        record = read_record(path)
    assert len(record) == len(table) - 1  # the cut row is gone, not read as 578 Pa + NaN
    columns = list(table.columns[1:])
    np.testing.assert_array_equal(record.data[columns], table.iloc[:-1][columns])


def test_short_line_inside_the_file_is_refused(tmp_path, table):
    lines = table.to_csv(index=False).splitlines()
    lines[10] = ",".join(lines[10].split(",")[:5])
    path = tmp_path / "mid.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordError, match=r"mid\.csv: line 11 has 5 fields but the header"):
        read_record(path)


def test_whole_last_line_without_line_end_warns(tmp_path, table):
    path = tmp_path / "noeol.csv"
    path.write_text(table.to_csv(index=False).rstrip("\n"))
    with pytest.warns(UserWarning, match="does not end with a line end"):
        record = read_record(path)
    assert len(record) == len(table)


def test_material_flow_in_microlitres_is_refused(tmp_path, table):
    from ajtwin.estimation import Twin

    table["material_flow_mL_s"] *= 1000.0
    path = tmp_path / "qm.csv"
    table.to_csv(path, index=False)
    record = read_record(path)  # inside the reader's wide range …
    with pytest.raises(
        RecordError, match=r"qm\.csv: column 'material_flow_mL_s': median .*× what the model"
    ):
        Twin.default(em=False).run(record)  # … but 1000× what the machine can give


def test_scale_check_passes_every_virtual_fault(virtual_print):
    """No scenario of the virtual printer trips the unit-slip check (no false refusal)."""
    from ajtwin.estimation.record_checks import check_output_scales
    from ajtwin.estimation.twin import Twin

    twin = Twin.default(em=False)
    for scenario in ("nozzle_clog", "carrier_leak", "pressure_sensor_drift", "atomizer_dropout"):
        record = simulate(scenario, seed=2)
        check_output_scales(
            twin.model.params, twin.spec.coefficients, record.inputs, record.outputs, 1.0, scenario
        )


def test_duplicated_column_is_named(tmp_path, table):
    text = table.to_csv(index=False).splitlines()
    header = text[0].split(",")
    header[-1] = "carrier_flow_sccm"  # material_flow's column now repeats column 3
    path = tmp_path / "dup.csv"
    path.write_text("\n".join([",".join(header), *text[1:]]) + "\n")
    with pytest.raises(RecordError, match=r"dup\.csv: columns 3 and 9 are both named "
                                          r"'carrier_flow_sccm'"):  # fmt: skip
        read_record(path)


def test_duplicated_parquet_column_is_named(tmp_path, table):
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays = [pa.array(table[c].to_numpy()) for c in table.columns] + [pa.array(table["time_s"])]
    pq.write_table(pa.Table.from_arrays(arrays, names=[*table.columns, "time_s"]),
                   tmp_path / "dup.parquet")  # fmt: skip
    with pytest.raises(RecordError, match=r"columns 1 and 10 are both named 'time_s'"):
        read_record(tmp_path / "dup.parquet")


@pytest.mark.parametrize(
    "meta, key",
    [
        ({"platen_speed_mm_s": -1}, "platen_speed_mm_s"),
        ({"platen_speed_mm_s": "fast"}, "platen_speed_mm_s"),
        ({"platen_speed_mm_s": 1e300}, "platen_speed_mm_s"),
        ({"seed": "x"}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"fault_onset_s": "soon"}, "fault_onset_s"),
        ({"fault_onset_s": -5}, "fault_onset_s"),
        ({"machine_id": 7}, "machine_id"),
        ({"format_version": 99}, "format_version"),
        ({"units": {"linewidth_um": 3}}, "units"),
    ],
)
def test_metadata_is_validated(tmp_path, table, meta, key):
    path = tmp_path / "m.csv"
    path.write_text("# meta: " + json.dumps(meta) + "\n" + table.to_csv(index=False))
    with pytest.raises(RecordError, match=rf"m\.csv: metadata '{key}'"):
        read_record(path)


def test_valid_metadata_still_reads(tmp_path, virtual_print):
    path = write_record(virtual_print, tmp_path / "ok.csv")
    back = read_record(path)
    assert back.meta["seed"] == virtual_print.meta["seed"]


@pytest.mark.parametrize(
    "option, value",
    [
        ("--gate", "0"),
        ("--gate", "nan"),
        ("--gate", "-1"),
        ("--gate", "-inf"),
        ("--vial-ml", "-1"),
        ("--vial-ml", "0"),
        ("--vial-ml", "1e300"),
        ("--vial-ml", "nan"),
        ("--vial-ml", "inf"),
        ("--vial-ml", "3"),  # = V_v: a full vial has no headspace
        ("--window", "1"),
        ("--every", "0"),
    ],
)
def test_estimate_options_are_validated(tmp_path, virtual_print, option, value):
    from ajtwin.cli.estimate import estimate

    path = write_record(virtual_print, tmp_path / "p.parquet")
    result = CliRunner().invoke(estimate, [str(path), "--out", str(tmp_path / "s.csv"),
                                           option, value])  # fmt: skip
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '{option}'" in result.output
    assert not (tmp_path / "s.csv").exists()


def test_bounded_float_accepts_the_valid_edges():
    import click

    from ajtwin.cli.options import BoundedFloat

    gate = BoundedFloat(0.0, float("inf"), allow_inf=True)
    assert gate.convert("inf", None, None) == float("inf")
    assert gate.convert("3", None, None) == 3.0
    assert gate.convert(1e-9, None, None) == 1e-9
    with pytest.raises(click.BadParameter):
        gate.convert("three", None, None)


@pytest.fixture(scope="module")
def small_video(tmp_path_factory, virtual_print):
    from ajtwin.cli.vision import render

    folder = tmp_path_factory.mktemp("video")
    record = write_record(virtual_print.window(0, 30), folder / "p.parquet")
    video = folder / "cam.avi"
    render.main([str(record), "--out", str(video), "--fps", "0.5", "--size", "480x320"],
                standalone_mode=False)  # fmt: skip
    return record, video


def test_ingest_video_applies_the_same_check_as_extract(small_video, monkeypatch):
    """`ingest --video --um-per-px 1e300` once stored 1e302 µm lines: one shared check now."""
    import ajtwin.vision.join as join
    from ajtwin.engine.video import join_video
    from ajtwin.vision.extract import VisionInputError

    record_path, video = small_video
    record = read_record(record_path)
    for bad in (1e300, 1e-4):
        with pytest.raises(VisionInputError, match="median linewidth .* is implausible"):
            join_video(record, video, bad, progress=False)
    calls = []
    original = join.check_linewidth_scale
    monkeypatch.setattr(join, "check_linewidth_scale",
                        lambda *a: calls.append(a) or original(*a))  # fmt: skip
    joined, *_ = join_video(record, video, 0.75, progress=False)
    from ajtwin.cli.vision import extract

    argv = [str(video), "--um-per-px", "1e300", "--out", str(video.with_suffix(".csv"))]
    result = CliRunner().invoke(extract, [*argv, "--no-progress"])
    assert result.exit_code == 1 and "implausible" in result.output
    assert len(calls) == 2  # ingest's join_video and extract both went through it
    assert np.nanmax(joined.outputs[:, 0]) < 200


def test_ingest_cli_refuses_and_stores_nothing(small_video, tmp_path):
    from ajtwin.cli.ingest import ingest
    from ajtwin.cli.machine import machine
    from ajtwin.store.registry import Registry

    record_path, video = small_video
    store = str(tmp_path / "v.sqlite")
    runner = CliRunner()
    assert runner.invoke(machine, ["add", "M", "--store", store]).exit_code == 0
    result = runner.invoke(ingest, ["--machine", "M", "--store", store, str(record_path),
                                    "--video", str(video), "--um-per-px", "1e300",
                                    "--no-progress"])  # fmt: skip
    assert result.exit_code == 1 and "implausible" in result.output
    assert Registry(store).last_print("M") is None


def test_truncated_video_warns(tmp_path):
    from ajtwin.cli.vision import render
    from ajtwin.vision.extract import TruncatedVideoWarning, open_source

    video = tmp_path / "cam.avi"
    render.main(["--out", str(video), "--duration", "5", "--size", "320x240"],
                standalone_mode=False)  # fmt: skip
    data = video.read_bytes()
    whole = open_source(video)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(whole)) == whole.count == 5
    cut = tmp_path / "trunc.avi"
    cut.write_bytes(data[: len(data) * 2 // 5])
    frames = open_source(cut)
    with pytest.warns(TruncatedVideoWarning, match=r"trunc\.avi: decoded \d of the 5 frames"):
        decoded = list(frames)
    assert 1 <= len(decoded) < 5


# --------------------------------------------------------------------------- #
# Errors that did not name file/row
# --------------------------------------------------------------------------- #
def test_vague_binary_utf16_parquet_named_csv(tmp_path, table, virtual_print):
    text = table.to_csv(index=False)
    cases = {
        "utf16.csv": (text.encode("utf-16"), "UTF-16"),
        "utf16le.csv": (text.encode("utf-16-le"), "UTF-16"),
        "bin.csv": (bytes(range(256)) * 8, "binary data"),
        "latin1.csv": (("# é\n" + text).encode("latin-1"), "line 1: not UTF-8"),
        "late.csv": (
            (text + "1,2,3,4,5,6,7,8,\xe9\n").encode("latin-1"),
            rf"line {len(table) + 2}",
        ),
    }
    write_record(virtual_print, tmp_path / "pq.parquet")
    cases["pq.csv"] = ((tmp_path / "pq.parquet").read_bytes(), "Parquet file with a .csv name")
    for name, (data, message) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(RecordError, match=message) as info:
            read_record(tmp_path / name)
        assert name in str(info.value)


def test_vague_nan_input_and_one_row_name_file_row_column(tmp_path, table):
    """A NaN input in a file is held as the live twin holds it (the warning names file,
    column and time); inputs handed to the twin directly must still be complete, and
    the error names row and column."""
    from ajtwin.estimation import Twin
    from ajtwin.io.records import PrintRecord

    table.loc[17, "carrier_flow_sccm"] = np.nan
    path = tmp_path / "nan.csv"
    table.to_csv(path, index=False)
    with pytest.warns(UserWarning, match=r"nan\.csv: 1 second\(s\) without complete inputs "
                                         r"\(carrier_flow_sccm: 1; .* t = 17 s\)"):  # fmt: skip
        record = read_record(path)
    Twin.default(em=False).run(record)
    direct = PrintRecord(table.reset_index(drop=True), {"source_file": "nan.csv"})
    with pytest.raises(RecordError, match=r"nan\.csv: row 18 \(t = 17 s\), column "
                                          r"'carrier_flow_sccm': input is missing"):  # fmt: skip
        Twin.default(em=False).run(direct)
    one = tmp_path / "one.csv"
    table.iloc[:1].to_csv(one, index=False)
    with pytest.raises(RecordError, match=r"one\.csv: the record has 1 row\(s\)"):
        Twin.default(em=False).run(read_record(one))


def test_vague_errors_reach_the_cli_with_the_file_name(tmp_path, table):
    from ajtwin.cli.estimate import estimate

    table["carrier_flow_sccm"] = table["carrier_flow_sccm"].astype(object)
    table.loc[17, "carrier_flow_sccm"] = "23,1"
    path = tmp_path / "text.csv"
    table.to_csv(path, index=False)
    result = CliRunner().invoke(estimate, [str(path), "--out", str(tmp_path / "s.csv")])
    assert result.exit_code == 1
    assert "text.csv: row 18" in result.output and "carrier_flow_sccm" in result.output


def test_records_written_by_pandas_round_trip_unchanged(tmp_path, virtual_print):
    """The stricter CSV reader still reads every value of a clean file exactly."""
    path = write_record(virtual_print, tmp_path / "p.csv")
    back = read_record(path)
    pd.testing.assert_frame_equal(back.data, virtual_print.data, check_exact=True)


def test_video_and_parameter_paths_are_checked_before_open(tmp_path):
    """The same regular-file check guards the camera reader and the parameter loader."""
    from ajtwin.model.parameters import load_parameters
    from ajtwin.vision.extract import VisionInputError, open_source

    fifo = tmp_path / "cam.png"
    os.mkfifo(fifo)
    with pytest.raises(VisionInputError, match="cam.png: is a FIFO"):
        _no_hang(lambda: open_source(fifo), fifo=fifo)
    with pytest.raises(InputFileError, match="is a directory, not a parameter file"):
        load_parameters(tmp_path)


def test_nul_byte_in_a_path_is_a_clear_error():
    with pytest.raises(RecordError, match="not a usable path"):
        read_record("bad\x00name.csv")


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "--out", "r.avi", "--fps", "nan"],  # was a ValueError traceback
        ["render", "--out", "r.avi", "--noise", "nan"],  # was accepted: a NaN-noise video
        ["render", "--out", "r.avi", "--tilt", "inf"],
        ["extract", "cam.avi", "--um-per-px", "0.75", "--out", "f.csv", "--start-offset", "nan"],
        ["simulate", "--scenario", "exp1", "--out", "x.parquet", "--duration-min", "nan"],
    ],
)
def test_float_options_refuse_nan_and_inf(tmp_path, argv):
    from ajtwin.cli import main

    result = CliRunner().invoke(main, argv)
    assert result.exit_code == 2 and "Invalid value for" in result.output, result.output
