"""The lab on one PostgreSQL server, with real processes: three served printers, three live
twins, an ingest and the dashboard, through kill -9 of a twin, a second host given a
machine name already written, a server restart and a lost network; every print counted
against the served printers. Long: behind `slow` (the default suite has the short real
instances: tests/test_store_postgres.py, a server restart under a live twin, a second twin
refused, two writers; tests/test_store.py, a killed ingest on both databases)."""

from __future__ import annotations

import pytest

from ajtwin.studies.lab_faults import MACHINES, run_lab


@pytest.mark.slow
def test_a_lab_on_one_postgresql_loses_and_duplicates_nothing_through_its_faults(tmp_path):
    minutes = 12.0  # 180 s at x4: the twins start within half of it on a busy machine
    report = run_lab(tmp_path / "lab", minutes=minutes, speed=4.0, outage_s=30.0)
    assert report["lost_or_duplicated"] == 0, report
    for name in MACHINES:
        entry = report["machines"][name]
        assert entry["prints"] == 1 and entry["samples"] == minutes * 60, (name, entry)
        assert entry["missing"] == entry["duplicated"] == 0, (name, entry)
        assert set(entry["sessions"]) == {"closed"}, (name, entry)
    second = report["faults"]["second_host"]
    assert second["refused"] and second["exit_code"] == 1, second
    assert report["ingested_prints"] == 1 and report["second_ingest_refused"]
    assert report["ingest_exit_code"] == 0
    assert report["dashboard_showed_live"] == sorted(MACHINES)
    assert report["logged"]["unreachable"] >= 1 and report["logged"]["reached_again"] >= 1
