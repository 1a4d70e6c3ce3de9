"""A job print's record and its program must agree before the twin runs, or nothing is
computed or stored.

The virtual printer's records agree with their program in every row (checked here for each
camera, read whole and spooled); each way a held-out attack broke the agreement — a wrong
--process-speed, metadata that says another speed, another program, a shutter column
contradicting the program, print times on another clock, a speed column in mm/min — stored
wrong states with status "ok" before, and is refused now with a sentence naming the column,
its value, the row and the program's line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli.estimate import estimate as estimate_command
from ajtwin.cli.ingest import ingest as ingest_command
from ajtwin.cli.job import job as job_group
from ajtwin.cli.simulate import simulate as simulate_command
from ajtwin.engine.ingest import ingest_record
from ajtwin.estimation import Twin
from ajtwin.estimation.print_time import check_job_record, program_for_record
from ajtwin.io.records import PrintRecord, open_record, read_record, write_record
from ajtwin.job.agreement import JobEvidence, RecordMismatch, check_record_agrees
from ajtwin.simulation import simulate
from ajtwin.simulation.job_print import CameraSettings, run_job_print
from ajtwin.store.registry import Registry

DATA = Path(__file__).resolve().parent / "data" / "prg" / "prg2svg"
NAFBOT = DATA / "1-nafbot.prg"
NAF6 = DATA / "4-naf 654321.prg"
NEVER_OPENS = "#0\nptp/ev (X,Y),0,0,10\nOUT1.0=1\nptp/e (X,Y),5,0\nOUT1.0=0\nSTOP\n"


@pytest.fixture(scope="module")
def record():
    """A 3-min print of the public 1-nafbot (2 mm/s), the camera trailing 5 mm behind."""
    return run_job_print(NAFBOT, "exp1", seed=1, duration_min=3.0).record


def changed(record, meta=None, **columns) -> PrintRecord:
    data = record.data.copy()
    for name, values in columns.items():
        data[name] = values
    return PrintRecord(data, record.meta if meta is None else meta)


def without_job(record) -> PrintRecord:
    """The record as a bare export: its job columns, no metadata naming the program."""
    return PrintRecord(record.data, {k: v for k, v in record.meta.items() if k != "job"})


def refusal(record, **job_options) -> str:
    job = program_for_record(record, job_options.pop("program", NAFBOT), held=False, **job_options)
    with pytest.raises(RecordMismatch) as caught:
        check_job_record(record, job)
    message = str(caught.value)
    assert message.endswith("Nothing was estimated or stored.")
    return message


@pytest.mark.parametrize("mode", ["trailing", "inspection", "at_nozzle"])
def test_the_virtual_printers_records_agree_with_their_program(tmp_path, mode):
    record = run_job_print(
        NAFBOT, "exp1", seed=2, duration_min=2.0, camera=CameraSettings(mode=mode)
    ).record
    job = program_for_record(record, NAFBOT, held=False)
    check_job_record(record, job)
    path = write_record(record, tmp_path / "p.parquet")
    with open_record(path) as spooled:  # the streamed twin's source: columns read off disk
        check_job_record(spooled, job)


def test_a_speed_given_wrong_is_refused_and_the_records_speed_taken_only_when_asked(record):
    """`ingest --process-speed 5` of a 2 mm/s print stored d_a 5.58 µm with status "ok"."""
    message = refusal(record, process_speed_mm_s=5.0)
    assert "column 'platen_speed_mm_s' is 2 mm/s at t = " in message
    assert "where the program moves at 5 mm/s (line " in message
    assert "metadata says 2 mm/s too: leave out --process-speed" in message
    # metadata that says 5 where the column says 2: refused, and read right when asked
    meta = {**record.meta, "job": {**record.meta["job"], "process_speed_mm_s": 5.0}}
    says_five = changed(record, meta)
    assert "give --process-speed 2 to read the program" in refusal(says_five)
    check_job_record(says_five, program_for_record(says_five, NAFBOT, process_speed_mm_s=2.0))


def test_a_record_is_refused_with_another_program(record):
    """A bare export of a nafbot print was ingested and mapped as a print of another program."""
    message = refusal(without_job(record), program=NAF6)
    assert "column 'shutter_open' is 0 (closed) at t = " in message
    assert "where the program prints throughout ±1 s (line " in message
    # metadata with "sha256": null cannot vouch for another program either
    meta = {**record.meta, "job": {**record.meta["job"], "sha256": None}}
    assert "shutter_open" in refusal(changed(record, meta), program=NAF6)


@pytest.mark.parametrize("shutter", ["all closed", "inverted"])
def test_a_shutter_column_that_contradicts_the_program_is_refused(record, shutter):
    values = 0.0 if shutter == "all closed" else 1.0 - record.shutter_open
    message = refusal(changed(record, shutter_open=values))
    assert "column 'shutter_open' is 0 (closed)" in message and "rows logged closed" in message


def test_print_times_on_another_clock_are_refused_and_the_shift_named(record):
    """printed_at_s 13.37 s early dropped 443 of 448 frames and gave d_a 0.96 µm."""
    tau = record.printed_at
    shifted = np.where(np.isfinite(tau), np.maximum(tau - 13.37, 0.0), np.nan)
    message = refusal(changed(record, printed_at_s=shifted))
    assert "column 'printed_at_s' is " in message and "from where the camera looked" in message
    assert "shifted by -13.4 s" in message
    zero = np.where(np.isfinite(tau), 0.0, np.nan)
    assert "camera rows do not fit the program" in refusal(changed(record, printed_at_s=zero))


def test_a_speed_column_in_mm_per_min_is_converted_by_its_header_or_refused(record, tmp_path):
    """120 'mm/s' gave d_a 10.9 µm blaming commissioning; `Stage Speed [mm/min]` was ignored."""
    per_min = record.data.assign(platen_speed_mm_s=60.0 * record.platen_speed)
    wrong = without_job(PrintRecord(per_min, record.meta))
    with pytest.raises(RecordMismatch, match="read as mm/min it would be 2 mm/s"):
        check_job_record(wrong)
    assert "the column looks like mm/min" in refusal(wrong)
    named = per_min.rename(columns={"platen_speed_mm_s": "Stage Speed [mm/min]"})
    path = tmp_path / "mmmin.csv"
    named.drop(columns=[c for c in named if c.startswith("true_")]).to_csv(path, index=False)
    with pytest.warns(UserWarning, match=r"'Stage Speed \[mm/min\]' → 'platen_speed_mm_s'"):
        read_back = read_record(path)
    np.testing.assert_allclose(read_back.platen_speed, record.platen_speed)
    check_job_record(read_back, program_for_record(read_back, NAFBOT, held=False))


def test_the_twin_refuses_before_computing_and_the_commands_store_nothing(record, tmp_path):
    path = write_record(record, tmp_path / "naf.parquet")
    job = program_for_record(record, NAFBOT, held=False, process_speed_mm_s=5.0)
    with pytest.raises(RecordMismatch), open_record(path) as spooled:  # the streamed twin
        Twin.default().run_streamed(spooled, sink=lambda first, run: None, job=job)
    store = tmp_path / "r.sqlite"
    Registry(store).add_machine("M")
    runner = CliRunner()
    common = ["--machine", "M", "--store", str(store), "--job", str(NAFBOT)]
    result = runner.invoke(ingest_command, [*common, "--process-speed", "5", str(path)])
    assert result.exit_code == 1 and "does not agree with" in result.output
    assert Registry(store).history("M").empty
    wrong_speed = runner.invoke(
        job_group,
        ["report", str(path), "--job", str(NAFBOT), "--process-speed", "5", "--tolerance",
         "74+-3", "--out", str(tmp_path / "fast"), "--no-progress"],
    )  # fmt: skip
    assert wrong_speed.exit_code == 1 and "does not agree with" in wrong_speed.output
    assert "is 2 mm/s" in wrong_speed.output and "moves at 5 mm/s" in wrong_speed.output
    assert not (tmp_path / "fast").exists()
    bare = write_record(without_job(record), tmp_path / "bare.parquet")
    report = runner.invoke(
        job_group,
        ["report", str(bare), "--job", str(NAF6), "--out", str(tmp_path / "r"), "--no-progress"],
    )
    assert report.exit_code == 1 and "column 'shutter_open'" in report.output
    assert not (tmp_path / "r").exists()


def test_the_check_weighs_rows_against_the_program_alone():
    """The module's example: four times the program's speed in every printing row."""
    from ajtwin.job import read_program_text

    job = read_program_text("ptp/e (X,Y),0,0\nOUT0.0=1\nptp/e (X,Y),20,0\nOUT0.0=0", path="p.prg")
    t = np.arange(10.0)
    rows = t.astype(int) + 1

    def evidence(speed):
        return JobEvidence("r.csv", t, rows, np.ones(10), np.full(10, speed), np.full(10, np.nan))

    check_record_agrees(evidence(2.1), job)  # within the speed tolerance (10 %)
    with pytest.raises(RecordMismatch, match=r"is 4 mm/s at t = 1 s \(row 2\).*\(line 3, "):
        check_record_agrees(evidence(4.0), job)


# --------------------------------------------------------------------------- #
# A program that prints nothing: a clear answer wherever a program is taken
# --------------------------------------------------------------------------- #
def test_a_program_that_prints_nothing_is_answered_in_words_by_every_command(record, tmp_path):
    never = tmp_path / "never.prg"
    never.write_text(NEVER_OPENS)
    runner = CliRunner()
    out = tmp_path / "n.parquet"
    made = runner.invoke(
        simulate_command, ["--job", str(never), "--duration-min", "2", "--out", str(out)]
    )
    assert made.exit_code == 1 and "prints nothing" in made.output and "OUT1.0" in made.output
    assert not out.exists()  # refused before the virtual printer ran
    path = write_record(without_job(record), tmp_path / "naf.parquet")
    for argv in (
        [str(path), "--job", str(never), "--out", str(tmp_path / "s.csv")],
        ["report", str(path), "--job", str(never), "--out", str(tmp_path / "r"), "--no-progress"],
    ):
        command = job_group if argv[0] == "report" else estimate_command
        result = runner.invoke(command, argv)
        assert result.exit_code == 1 and "prints nothing" in result.output, result.output


def test_control_simulate_with_a_program_that_prints_nothing_says_so(tmp_path):
    """It scored "rms 0.00 µm" on a part that was never printed."""
    from ajtwin.cli.control import control

    never = tmp_path / "never.prg"
    never.write_text(NEVER_OPENS)
    result = CliRunner().invoke(
        control,
        ["simulate", "--scenario", "exp1", "--target-linewidth", "74", "--duration-min", "3",
         "--strategies", "mpc_twin", "--job", str(never), "--out", str(tmp_path / "c"),
         "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 1 and "prints nothing" in result.output, result.output


def test_a_stored_print_whose_program_prints_nothing_is_answered_not_a_server_error(tmp_path):
    """Stored through `live --job` before such programs were refused, its part map was an
    HTTP 500 on the dashboard and a traceback in `job report --machine`."""
    from fastapi.testclient import TestClient

    from ajtwin.web.app import create_app

    store = tmp_path / "r.sqlite"
    registry = Registry(store)
    registry.add_machine("M")
    entry = {"program": "never.prg", "program_bytes": NEVER_OPENS.encode(), "settings": {}}
    ingest_record(registry, "M", simulate("exp1", seed=3, duration_min=2.0), job=entry)
    registry.close()
    app = create_app(store)
    client = TestClient(app, base_url="http://127.0.0.1", raise_server_exceptions=False)
    answer = client.get("/api/machine/M/print/1/part")
    app.state.view.close()
    assert answer.status_code == 404
    assert "its part cannot be mapped" in answer.json()["error"]
    assert "prints nothing" in answer.json()["error"]
    report = CliRunner().invoke(
        job_group, ["report", "--machine", "M", "--store", str(store), "--out", str(tmp_path)]
    )
    assert report.exit_code == 1 and "prints nothing" in report.output


def test_the_evidence_of_a_long_record_is_a_sample_of_its_rows():
    from ajtwin.job.agreement import sample_rows

    rows = sample_rows(1_209_600)
    assert rows.size == 10_000 and rows[0] == 0 and rows[-1] == 1_209_599
    assert (np.diff(rows) > 0).all()
    np.testing.assert_array_equal(sample_rows(600), np.arange(600))
