"""A record held on disk and read in pieces is the record read whole.

``open_record`` keeps a record's 1 Hz table in an unlinked temporary file and gives it a
piece at a time; ``ingest`` runs the twin over those pieces so that its memory does not
grow with the print. Everything it gives must be what the whole table gives: the table
(pieces of 5 rows against one block), the reader's notes, the content hash (duplicates
must be found across both ways), the twin's run chunk by chunk and the stored print — on a
job print too, its camera filed at print times through one delay line as the rows are read.
"""

from __future__ import annotations

import errno
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import ajtwin.estimation.twin as twin_module
import ajtwin.io.spool as spool_module
from ajtwin.engine.ingest import ingest_file, ingest_record
from ajtwin.engine.print_job import job_entry
from ajtwin.estimation.print_time import program_for_record
from ajtwin.estimation.twin import Twin
from ajtwin.io.records import (
    CSV_META_PREFIX,
    PrintRecord,
    RecordError,
    open_record,
    read_record,
    write_record,
)
from ajtwin.simulation import simulate
from ajtwin.simulation.job_print import simulate_job
from ajtwin.store.registry import Registry, record_hash

#: the atomizer's dropout 20 min into the print (an event for the detectors to raise)
ONSET_20 = {"fault": {"onset_min": 20.0}}


def _read(path, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        record = read_record(path, **kwargs)
    return record, [str(w.message) for w in caught]


def _outage_log(tmp_path):
    """A 10 Hz log with outages of its inputs (one before any complete inputs, one of
    3 s and one of 12 s, the longest, from t = 20 s), an operator's note, and a material
    flow exported with 3 decimals (all zero: treated as missing)."""
    base = simulate("exp1", seed=2, duration_min=1.0).data.iloc[:, :9]
    t = np.arange(0.0, 59.95, 0.1)
    table = pd.DataFrame({"time_s": t})
    for column in base.columns[1:]:
        table[column] = np.interp(t, base["time_s"], base[column])
    table["material_flow_mL_s"] = 0.0
    inputs = ["atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm"]
    for start, stop in ((0.0, 2.0), (5.0, 8.0), (20.0, 32.0)):
        table.loc[(t >= start - 0.5) & (t < stop - 0.5), inputs] = np.nan
    table["note"] = ["wiped" if k == 300 else "" for k in range(len(t))]
    path = tmp_path / "outage.csv"
    table.to_csv(path, index=False, float_format="%.3f")
    return path


def test_a_record_read_in_pieces_of_five_rows_is_the_record_read_whole(tmp_path, monkeypatch):
    path = _outage_log(tmp_path)
    whole, notes = _read(path)
    monkeypatch.setattr(spool_module, "SPOOL_BLOCK_ROWS", 5)
    pieces, piece_notes = _read(path)
    pd.testing.assert_frame_equal(pieces.data, whole.data)
    assert piece_notes == notes
    # the hold, by hand: 2 s dropped before the first complete inputs, 3 + 12 s held
    held = [n for n in notes if "without complete inputs" in n]
    assert len(held) == 1, notes
    assert "15 second(s) without complete inputs" in held[0]
    assert "the longest run 12 s from t = 20 s" in held[0]
    assert "the first 2 second(s), before any complete inputs, dropped" in held[0]
    assert whole.data["time_s"].iloc[0] == 2.0
    assert np.isnan(whole.data["material_flow_mL_s"]).all()
    assert whole.data["note"].iloc[30 - 2] == "wiped"
    assert np.isnan(whole.data.loc[18:29, "linewidth_um"]).all()  # t = 20 … 31 s: no outputs
    np.testing.assert_array_equal(
        whole.data.loc[18:29, "carrier_flow_sccm"], whole.data.loc[17, "carrier_flow_sccm"]
    )


def test_pieces_of_a_record_held_on_disk_are_its_rows(tmp_path):
    path = _outage_log(tmp_path)
    whole, _ = _read(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with open_record(path) as held:
            parts = [held.piece(a, a + 7).data for a in range(0, len(held), 7)]
            assert len(held) == len(whole) and held.duration_s == whole.duration_s
            assert [held.time_s[k] for k in (0, -1)] == [whole.time_s[0], whole.time_s[-1]]
            assert held.columns == list(whole.data.columns)
            np.testing.assert_array_equal(held.column("linewidth_um"), whole.data["linewidth_um"])
    joined = pd.concat(parts, ignore_index=True)
    pd.testing.assert_frame_equal(joined, whole.data)


@pytest.mark.parametrize("version", [1, 2])
def test_a_record_held_on_disk_hashes_as_the_record_loaded_whole(tmp_path, monkeypatch, version):
    record = simulate("exp1", seed=4, duration_min=3.0)
    data = record.data.copy()
    data["note"] = ["ok" if k % 50 == 0 else "" for k in range(len(data))]

    def write(table, name):
        if version == 1:  # the job columns filled by the reader
            path = tmp_path / f"{name}.csv"
            path.write_text(CSV_META_PREFIX + '{"format_version": 1}\n' + table.to_csv(index=False))
            return path
        return write_record(PrintRecord(table, record.meta), tmp_path / f"{name}.parquet")

    path = write(data, "p")
    monkeypatch.setattr(spool_module, "SPOOL_BLOCK_ROWS", 11)
    with open_record(path) as held:
        assert record_hash(held) == record_hash(held.load())
        assert ("shutter_open" in held.columns) == (version == 1)
    changed = data.copy()
    changed.loc[100, "sheath_pressure_Pa"] += 1e-6
    other = write(changed, "q")
    with open_record(path) as a, open_record(other) as b:
        assert record_hash(a) != record_hash(b)


def test_reading_a_record_leaves_no_file_behind(tmp_path, monkeypatch):
    spool_dir = tmp_path / "spool"
    spool_dir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spool_dir))
    path = write_record(simulate("exp1", seed=1, duration_min=2.0), tmp_path / "p.parquet")
    with open_record(path) as held:
        # unlinked as it is made: a killed process leaves nothing in the folder
        assert list(spool_dir.iterdir()) == []
        assert len(held.load()) == 120
    read_record(path)
    assert list(spool_dir.iterdir()) == []


def test_no_room_for_the_table_on_disk_is_a_clear_error(tmp_path, monkeypatch):
    path = write_record(simulate("exp1", seed=1, duration_min=2.0), tmp_path / "p.parquet")
    made = tempfile.TemporaryFile

    class Full:
        def __init__(self, *args, **kwargs):
            self.file = made(*args, **kwargs)

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.file, name)

    monkeypatch.setattr(tempfile, "TemporaryFile", Full)
    with pytest.raises(RecordError) as caught:
        read_record(path)
    said = str(caught.value)
    assert str(path) in said and "No space left on device" in said and "TMPDIR" in said


def _chunks(store):
    def sink(first, chunk):
        store.append((first, chunk))

    return sink


@pytest.mark.parametrize("start", ["initial fit", "previous end"])
def test_the_twin_over_a_record_read_in_pieces_is_the_twin_over_it_whole(
    tmp_path, monkeypatch, start
):
    record = simulate("atomizer_dropout", seed=3, duration_min=40.0, overrides=ONSET_20)
    path = write_record(record, tmp_path / "p.parquet")
    loaded = read_record(path)
    begin = None
    if start == "previous end":
        previous = Twin.default().run(simulate("exp1", seed=2, duration_min=5.0))
        begin = (previous.end_mean, previous.end_cov)
    # pieces that cut EM's chunks and windows anywhere: the input response carried over
    monkeypatch.setattr(twin_module, "STREAM_READ_ROWS", 137)
    monkeypatch.setattr(spool_module, "SPOOL_BLOCK_ROWS", 1000)
    whole, pieces = [], []
    run = Twin.default().run(loaded, start=begin, sink=_chunks(whole))
    with open_record(path) as held:
        streamed = Twin.default().run_streamed(held, start=begin, sink=_chunks(pieces))
    assert len(whole) == len(pieces) > 8
    for (a, x), (b, y) in zip(whole, pieces, strict=True):
        assert a == b
        for name in ("means", "covariances", "predicted_outputs", "nis"):
            np.testing.assert_array_equal(getattr(x.filtered, name), getattr(y.filtered, name))
        np.testing.assert_array_equal(x.theta_per_step, y.theta_per_step)
        np.testing.assert_array_equal(x.seen, y.seen)
        np.testing.assert_array_equal(x.measurements, y.measurements)
    pd.testing.assert_frame_equal(run.theta_history, streamed.theta_history)
    assert len(run.theta_history) == 7  # at 120 s, then every 300 s from 600 s to 2100 s
    np.testing.assert_array_equal(run.end_mean, streamed.end_mean)
    np.testing.assert_array_equal(run.end_cov, streamed.end_cov)
    assert streamed.n_steps == len(loaded) and streamed.time_s is None
    assert run.visibility_notes() == streamed.visibility_notes()


def test_no_camera_print_read_in_pieces_says_what_its_data_cannot_see(tmp_path):
    record = simulate("exp1", seed=1, duration_min=12.0)
    data = record.data.drop(columns=["linewidth_um", "overspray_um"])
    path = write_record(PrintRecord(data, record.meta), tmp_path / "p.parquet")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = read_record(path)
        config = {"droplet_prior_um": 3.5, "droplet_prior_std_um": 0.2}
        twin = Twin.default(**config)
        run = twin.run(loaded, sink=lambda first, chunk: None)
        with open_record(path) as held:
            streamed = Twin.default(**config).run_streamed(held, sink=lambda first, chunk: None)
    notes = streamed.visibility_notes()
    assert notes == run.visibility_notes()
    assert any("droplet" in n and "cannot see" in n for n in notes), notes


def test_ingest_of_a_file_in_pieces_stores_what_a_whole_read_stores(tmp_path, monkeypatch):
    monkeypatch.setattr(twin_module, "STREAM_READ_ROWS", 211)
    record = simulate("atomizer_dropout", seed=5, duration_min=30.0, overrides=ONSET_20)
    path = write_record(record, tmp_path / "p.pq")
    stored = {}
    for way in ("pieces", "whole"):
        registry = Registry(tmp_path / f"{way}.sqlite")
        registry.add_machine("M")
        if way == "pieces":
            result = ingest_file(registry, "M", path)
        else:
            result = ingest_record(registry, "M", read_record(path), source=str(path))
        stored[way] = (registry, result)
    (reg_a, a), (reg_b, b) = stored["pieces"], stored["whole"]
    assert not a.duplicate and a.content_hash == b.content_hash
    assert a.summary == b.summary
    assert [(e.detected_s, e.description) for e in a.events] == [
        (e.detected_s, e.description) for e in b.events
    ]
    arrays_a, arrays_b = reg_a.print_arrays(a.print_id), reg_b.print_arrays(b.print_id)
    assert sorted(arrays_a) == sorted(arrays_b)
    for name, values in arrays_a.items():
        np.testing.assert_array_equal(values, arrays_b[name], err_msg=name)
    # one print, read either way, is found again
    again = ingest_record(reg_a, "M", read_record(path), source=str(path))
    assert again.duplicate and again.print_id == a.print_id


PROGRAM = Path(__file__).parent / "data" / "prg" / "prg2svg" / "4-naf 654321.prg"


@pytest.fixture(scope="module")
def job_print(tmp_path_factory):
    """A 25-min print of a public program with the camera 5 mm behind the nozzle (its
    frames filed up to 126 s after they were taken)."""
    record = simulate_job(PROGRAM, "exp1", seed=2, duration_min=25.0)
    return write_record(record, tmp_path_factory.mktemp("job") / "job.parquet")


@pytest.mark.parametrize("read_rows", [50, 4096])
def test_a_job_print_read_in_pieces_is_filed_and_run_as_read_whole(
    job_print, monkeypatch, read_rows
):
    monkeypatch.setattr(twin_module, "STREAM_READ_ROWS", read_rows)
    loaded = read_record(job_print)
    job = program_for_record(loaded, PROGRAM)
    whole, pieces = [], []
    run = Twin.default().run(loaded, job=job, sink=_chunks(whole))
    with open_record(job_print) as held:
        streamed = Twin.default().run_streamed(held, job=job, sink=_chunks(pieces))
    # the blocks the core commits, the same either way, tile the print
    assert len(whole) == len(pieces) >= 6
    assert [a for a, _ in whole] == list(np.cumsum([0] + [len(x.time_s) for _, x in whole[:-1]]))
    assert sum(len(x.time_s) for _, x in whole) == len(loaded)
    for (a, x), (b, y) in zip(whole, pieces, strict=True):
        assert a == b
        for name in ("means", "covariances", "nis"):
            np.testing.assert_array_equal(getattr(x.filtered, name), getattr(y.filtered, name))
        for name in ("measurements", "line_factors", "n_camera", "seen", "inputs"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
    pd.testing.assert_frame_equal(run.theta_history, streamed.theta_history)
    np.testing.assert_array_equal(run.end_mean, streamed.end_mean)
    assert streamed.camera_counts == run.camera_counts
    assert run.camera_counts["horizon_s"] == 126.0 and run.camera_counts["filed"] > 1000


def test_ingest_of_a_job_print_in_pieces_stores_what_a_whole_read_stores(job_print, tmp_path):
    stored = {}
    for way in ("pieces", "whole"):
        registry = Registry(tmp_path / f"{way}.sqlite")
        registry.add_machine("M")
        if way == "pieces":
            result = ingest_file(registry, "M", job_print, program=PROGRAM)
        else:
            record = read_record(job_print)
            entry = job_entry(PROGRAM, record)
            result = ingest_record(registry, "M", record, source=str(job_print), job=entry)
        stored[way] = (registry, result)
    (reg_a, a), (reg_b, b) = stored["pieces"], stored["whole"]
    assert a.summary == b.summary and a.content_hash == b.content_hash
    arrays_a, arrays_b = reg_a.print_arrays(a.print_id), reg_b.print_arrays(b.print_id)
    assert sorted(arrays_a) == sorted(arrays_b) and "line_factors" in arrays_a
    for name, values in arrays_a.items():
        np.testing.assert_array_equal(values, arrays_b[name], err_msg=name)
    assert reg_a.print_job(a.print_id)["sha256"] == reg_b.print_job(b.print_id)["sha256"]


def test_job_columns_are_checked_over_the_whole_file_when_it_is_opened(tmp_path, monkeypatch):
    record = simulate_job(PROGRAM, "exp1", seed=3, duration_min=1.0)
    monkeypatch.setattr(spool_module, "SPOOL_BLOCK_ROWS", 7)
    rounded = record.data.copy()
    rounded.loc[[3, 40], "shutter_open"] = 0.3
    path = write_record(PrintRecord(rounded, record.meta), tmp_path / "rounded.parquet")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_record(path)
    said = [str(w.message) for w in caught if "shutter_open" in str(w.message)]
    assert len(said) == 1 and "holds 2 values between 0 and 1" in said[0], said
    broken = record.data.copy()
    broken.loc[30, "shutter_open"] = 2.0
    path = write_record(PrintRecord(broken, record.meta), tmp_path / "broken.parquet")
    with pytest.raises(RecordError, match=r"row 31 \(t = 30 s\), column 'shutter_open'"):
        open_record(path)
