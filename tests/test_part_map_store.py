"""The job kept with a print: ingest --job, history, job report from the registry, an
older registry after the migration, the live twin's part map and stored job."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.apps.quality.live_map import LivePartMap
from ajtwin.apps.quality.part_map import Tolerance, portion_table, sample_points
from ajtwin.cli.ingest import ingest
from ajtwin.cli.job import job as job_group
from ajtwin.cli.machine import machine
from ajtwin.engine.ingest import ingest_record
from ajtwin.engine.part_live import follow_engine
from ajtwin.engine.print_job import entry_job, job_entry
from ajtwin.io.records import write_record
from ajtwin.simulation import JobSettings, run_job_print, simulate
from ajtwin.store import registry as R
from ajtwin.store.registry import Registry

PROGRAM = Path("tests/data/prg/prg2svg/2 and 6-Au.prg").resolve()
OTHER = Path("tests/data/prg/prg2svg/3-PPbot.prg").resolve()


def run(command, *args):
    result = CliRunner().invoke(command, [str(a) for a in args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


@pytest.fixture(scope="module")
def job_print_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("print")
    record = run_job_print(PROGRAM, "exp1", 3, duration_min=4.0).record
    path = folder / "job_print.parquet"
    write_record(record, path)
    return path


def test_ingest_with_its_job_stores_it_and_history_names_it(job_print_file, tmp_path):
    store = tmp_path / "r.sqlite"
    run(machine, "add", "lab1", "--store", store)
    # the wrong program is refused before anything is stored
    bad = run(ingest, "--machine", "lab1", job_print_file, "--job", OTHER, "--store", store)
    assert bad.exit_code == 1 and "is not the program this print ran" in bad.output
    assert Registry(store).machine("lab1")["n_prints"] == 0
    lonely = run(ingest, "--machine", "lab1", job_print_file, "--tolerance", "74+-2",
                 "--store", store)  # fmt: skip
    assert lonely.exit_code == 2 and "go with --job" in lonely.output
    done = run(ingest, "--machine", "lab1", job_print_file, "--job", PROGRAM,
               "--tolerance", "74+-2", "--no-progress", "--store", store)  # fmt: skip
    assert done.exit_code == 0, done.output
    assert f"job {PROGRAM.name} kept with the print" in done.output
    with Registry(store) as reg:
        row = reg.last_print("lab1")
        entry = reg.print_job(row["id"])
        assert entry["program"] == PROGRAM.name
        assert entry["program_bytes"] == PROGRAM.read_bytes()  # the program, byte for byte
        assert entry["settings"]["tolerance_um"] == [72.0, 76.0]
        assert entry["settings"]["process_speed_mm_s"] == 2.0
        assert entry["settings"]["repeat_to_s"] == 240.0  # as the print looped it
        arrays = reg.print_arrays(row["id"])
        assert {"shutter_open", "platen_speed_mm_s", "printed_at_s"} <= set(arrays)
        assert reg.history("lab1")["program"].tolist() == [PROGRAM.name]
    shown = run(machine, "history", "lab1", "--store", store)
    assert shown.exit_code == 0 and PROGRAM.name in shown.output

    # the stored print's report is the file's report (the same twin run, re-run)
    out_file, out_store = tmp_path / "from_file", tmp_path / "from_store"
    a = run(job_group, "report", job_print_file, "--job", PROGRAM, "--tolerance", "74+-2",
            "--out", out_file, "--no-progress")  # fmt: skip
    b = run(job_group, "report", "--machine", "lab1", "--out", out_store, "--no-progress",
            "--store", store)  # fmt: skip
    assert a.exit_code == 0 and b.exit_code == 0, (a.output, b.output)
    first = pd.read_csv(out_file / "strokes.csv")
    second = pd.read_csv(out_store / "strokes.csv")
    pd.testing.assert_frame_equal(first, second)
    assert "lab1 print 1" in b.output and "away from the stored end state" not in b.output


def test_a_job_looped_side_by_side_is_kept_and_read_back_as_the_print_ran_it(tmp_path):
    """A print that looped its program as parts side by side: the record's reading and the
    registry's (ingest --job, then the stored entry) give the same job — the same runs at
    the same places — because one function reads both."""
    from ajtwin.estimation.print_time import program_for_record

    record = run_job_print(
        PROGRAM, "exp1", 3, duration_min=4.0, job_settings=JobSettings(repeat_pitch_mm=(35.0, 10.0))
    ).record
    assert record.meta["job"]["repeat_pitch_mm"] == [35.0, 10.0]
    from_record = program_for_record(record, PROGRAM)
    assert from_record.repetitions > 1 and np.ptp(from_record.repetition_offsets_mm[:, 0]) > 0
    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("lab")
    result = ingest_record(reg, "lab", record, job=job_entry(PROGRAM, record))
    entry = reg.print_job(result.print_id)
    assert entry["settings"]["repeat_pitch_mm"] == [35.0, 10.0]
    from_store = entry_job(entry)
    np.testing.assert_array_equal(
        from_store.repetition_offsets_mm, from_record.repetition_offsets_mm
    )
    pd.testing.assert_frame_equal(from_store.timeline(), from_record.timeline())
    # overprinted instead (no pitch): the same part printed again, runs at one place
    again = entry_job({**entry, "settings": {**entry["settings"], "repeat_pitch_mm": None}})
    assert np.ptp(again.repetition_offsets_mm, axis=0).max() == 0.0
    reg.close()


def test_job_report_of_a_log_that_names_no_job_takes_the_looping_from_the_options(tmp_path):
    """A machine log that does not say how the job was looped, given --repeat-to and
    --repeat-pitch-mm, is mapped as the same print whose record says so."""
    from ajtwin.io.records import PrintRecord

    record = run_job_print(
        PROGRAM, "exp1", 3, duration_min=4.0, job_settings=JobSettings(repeat_pitch_mm=(35.0, 10.0))
    ).record
    named = tmp_path / "named.parquet"
    write_record(record, named)
    meta = {k: v for k, v in record.meta.items() if k != "job"}
    bare = tmp_path / "bare.parquet"
    write_record(PrintRecord(record.data, meta), bare)
    common = ["--job", PROGRAM, "--tolerance", "74+-2", "--no-progress"]
    a = run(job_group, "report", named, "--out", tmp_path / "a", *common)
    looping = ["--repeat-to", record.meta["job"]["repeat_to_s"], "--repeat-pitch-mm", "35,10"]
    b = run(job_group, "report", bare, "--out", tmp_path / "b", *common, *looping)
    assert a.exit_code == 0 and b.exit_code == 0, (a.output, b.output)
    first = pd.read_csv(tmp_path / "a" / "strokes.csv")
    second = pd.read_csv(tmp_path / "b" / "strokes.csv")
    assert first["repetition"].max() >= 1
    pd.testing.assert_frame_equal(first, second)


def test_an_older_registry_opens_after_the_migration_and_keeps_its_prints(tmp_path, job_print_file):
    store = tmp_path / "v5.sqlite"
    reg = Registry(store)
    reg.add_machine("old")
    ingest_record(reg, "old", simulate("exp1", seed=1, duration_min=1.0), source="x")
    reg.close()
    # as schema 5 left it: no job table (the tables of later migrations are created if missing)
    with sqlite3.connect(store) as conn:
        conn.execute("DROP TABLE print_jobs")
        conn.execute("UPDATE info SET value = '5' WHERE key = 'schema_version'")
    conn.close()
    tables = {r[0] for r in sqlite3.connect(store).execute("SELECT name FROM sqlite_master")}
    assert "print_jobs" not in tables
    reg = Registry(store)
    # (later migrations follow this one: one message each)
    assert len(reg.migrated) == R.SCHEMA_VERSION - 5
    assert reg.migrated[0] == (f"{store}: migrated registry schema 5 → 6 (the job (machine "
                               "program) each print ran: print_jobs)")  # fmt: skip
    assert reg.info("schema_version") == str(R.SCHEMA_VERSION)
    history = reg.history("old")
    assert len(history) == 1 and history["program"].tolist() == [""]
    assert reg.print_job(int(history["print_id"][0])) is None
    reg.close()
    no_job = run(job_group, "report", "--machine", "old", "--out", tmp_path / "o",
                 "--store", store, "--no-progress")  # fmt: skip
    assert no_job.exit_code == 1 and "stored without its job" in no_job.output


def test_a_damaged_stored_program_is_named(tmp_path, job_print_file):
    store = tmp_path / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("lab")
    from ajtwin.io.records import read_record

    record = read_record(job_print_file)
    ingest_record(reg, "lab", record, job=job_entry(PROGRAM, record))
    reg.close()
    conn = sqlite3.connect(store)
    conn.execute("UPDATE print_jobs SET program_blob = x'00010203'")
    conn.commit()
    conn.close()
    with Registry(store) as reg, pytest.raises(R.RegistryError, match="damaged at print 1"):
        reg.print_job(reg.last_print("lab")["id"])


def test_the_live_twin_maps_the_final_part_as_the_batch_filter_does_and_stores_the_job(
    tmp_path,
):
    """Fed a job print sample by sample (the camera trailing, frames filed at their print
    times), the live map hands out a portion only once its seconds are final — H rows after
    it was printed — with the line of the filtered states the batch twin has (stream =
    batch), evaluated by the twin's own line evaluation; the finished print is stored with
    its job and the speed-law factors of its filed steps."""
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation import Twin
    from ajtwin.estimation.print_time import print_context
    from ajtwin.estimation.samples import Sample

    job_print = run_job_print(PROGRAM, "exp1", 2, duration_min=3.0)
    record = job_print.record
    entry = job_entry(PROGRAM, record, tolerance=Tolerance(72.0, 76.0))
    job = entry_job(entry)
    context = print_context(record, job)
    horizon = context.horizon_s
    assert record.meta["camera"]["mode"] == "trailing" and 5 <= horizon < 120
    reg = Registry(tmp_path / "r.sqlite")
    engine = LiveEngine(reg, asynchronous=False)
    engine.jobs["m"] = entry
    engine.open("m", print_context=context)
    part = LivePartMap(entry_job(entry), tolerance=Tolerance(72.0, 76.0))
    chunks, fed = [], [0]  # chunks with the row that made them; rows fed so far
    follow_engine(engine, "m", part, lambda machine, chunk: chunks.append((fed[0], chunk)))
    columns = zip(record.time_s, record.inputs, record.outputs, record.shutter_open,
                  record.platen_speed, record.printed_at)  # fmt: skip
    for row, values in enumerate(columns):
        fed[0] = row
        engine.feed("m", Sample(*values))
    fed[0] = len(record)  # what the end of the print makes final
    print_id = engine.close("m")
    assert reg.print_job(print_id)["program"] == PROGRAM.name
    # a portion is handed out once final: printed at least H s before the row that did it
    for at, chunk in chunks:
        if "portions" in chunk and at < len(record):
            latest = max(chunk["portions"]["printed_to_s"])
            assert latest <= record.time_s[at] - horizon + 1e-6
    assert any(at < len(record) for at, c in chunks if "portions" in c)
    live = {
        k: np.concatenate([c["portions"][k] for _, c in chunks if "portions" in c])
        for k in ("index", "stroke", "portion", "lw_mean_um", "lw_hi_um", "p_out")
    }
    n = len(live["index"])
    assert np.array_equal(live["index"], np.arange(n))
    # the batch twin over the same print as it ran, its filtered line at the same points
    run_ = Twin.default().run(record, job=job)
    assert run_.camera_counts["horizon_s"] == horizon
    portions = part.job.portions(1.0)
    portions = portions[portions["t_to_s"] <= record.time_s[-1] + 1e-9].reset_index(drop=True)
    assert n == len(portions) > 100
    points = sample_points(part.job, portions)
    line = run_.line_at(points["time_s"], points["speed_mm_s"], smoothed=False)
    points["lw_mean_um"], points["lo_mean_um"] = line.linewidth_um, line.overspray_um
    points["lw_sd_um"], points["lo_sd_um"] = line.linewidth_std_um, line.overspray_std_um
    batch = portion_table(portions, points, Tolerance(72.0, 76.0))
    # each portion was evaluated when it was final, from the states up to then, which are
    # the batch filter's (stream = batch): equal to the page's rounding (0.001 µm, 1e-4)
    np.testing.assert_allclose(live["lw_mean_um"], batch["lw_mean_um"], rtol=0, atol=5.01e-4)
    np.testing.assert_allclose(live["lw_hi_um"], batch["lw_hi_um"], rtol=0, atol=5.01e-4)
    np.testing.assert_allclose(live["p_out"], batch["p_out"], rtol=0, atol=5.01e-5)
    assert batch["flagged"].any() and not batch["flagged"].all()
    # the stored live print keeps its filed steps' factors: its map re-runs the same filter
    arrays = reg.print_arrays(print_id)
    np.testing.assert_array_equal(arrays["line_factors"], run_.line_factors)
    np.testing.assert_array_equal(arrays["measurements"], run_.measurements)


def test_a_served_virtual_printer_runs_the_job():
    """``ajtwin printer serve --job``: the served rows have no line while the camera sees no
    trace, and the same record as the batch job print."""
    from ajtwin.live.printer_server import VirtualMachine

    vm = VirtualMachine("vm", "exp1", seed=4, duration_min=2.0, job=PROGRAM)
    rows = vm.rows(120, 120)
    batch = run_job_print(PROGRAM, "exp1", 4, duration_min=2.0).record
    linewidth = rows[:, 4]  # time, 3 inputs, then L_w, L_o, P_c, P_s, Q_m
    assert np.isnan(linewidth).any() and np.isfinite(linewidth).any()
    np.testing.assert_array_equal(np.isnan(linewidth), np.isnan(batch.outputs[:120, 0]))
