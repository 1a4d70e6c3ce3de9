"""Calibrations and maintenance events are part of the registry's schema (migration 4):
export → import carries them, compact keeps them, schema-3 registries migrate."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.engine.chain import chain_start
from ajtwin.engine.start import machine_start
from ajtwin.store import registry as R
from ajtwin.store.archive import export_machine, import_machine
from ajtwin.store.calibration import (
    active_calibration,
    calibration_history,
    maintenance_history,
    record_maintenance,
    save_calibration,
)
from ajtwin.store.compaction import compact
from ajtwin.store.registry import Registry

CAL_TABLES = {"calibrations", "maintenance_events"}


@pytest.fixture(scope="module")
def commissioned():
    from ajtwin.estimation.commission import commission
    from ajtwin.simulation.printer import run_virtual_print

    vp = run_virtual_print("commissioning", seed=11, machine_seed=3)
    return commission(vp.record)


def _history(reg, name) -> dict:
    """Everything the registry keeps of a machine's calibrations and maintenance."""
    active = active_calibration(reg, name)
    start = machine_start(reg, name, chain_start(reg, name))
    return {
        "calibrations": calibration_history(reg, name).drop(columns="id"),
        "maintenance": maintenance_history(reg, name).drop(columns="id"),
        "active": active,
        "start": start,
    }


def _assert_same(a: dict, b: dict):
    pd.testing.assert_frame_equal(a["calibrations"], b["calibrations"])
    pd.testing.assert_frame_equal(a["maintenance"], b["maintenance"])
    x, y = a["active"], b["active"]
    for key in ("created_at", "created_unix", "source", "after_print_seq", "std", "prior_std",
                "determined", "priors", "notes", "noise_factors", "calibration"):  # fmt: skip
        assert x[key] == y[key], key
    for key in ("end_mean", "end_cov", "calibration_cov"):
        assert np.array_equal(x[key], y[key]), key
    s, t = a["start"], b["start"]
    assert s["started_from"] == t["started_from"] and s["maintenance"] == t["maintenance"]
    assert np.array_equal(s["start"][0], t["start"][0])
    assert np.array_equal(s["start"][1], t["start"][1])
    assert np.array_equal(s["theta"], t["theta"])
    assert s["twin_kwargs"]["calibration"] == t["twin_kwargs"]["calibration"]
    assert np.array_equal(s["twin_kwargs"]["calibration_cov"], t["twin_kwargs"]["calibration_cov"])


def test_new_registry_has_the_tables_at_schema_4(store):
    reg = Registry(store)
    assert CAL_TABLES <= reg._db.tables() and reg.info("schema_version") == str(R.SCHEMA_VERSION)
    assert R.SCHEMA_VERSION >= 5
    assert {"calibrations", "maintenance_events"} <= set(R.MACHINE_TABLES)
    # schema 5: the detectors' long-run statistics per print and per calibration
    for table in ("prints", "calibrations"):
        assert "long_run_json" in reg._db.columns(table), table


def test_export_import_carries_calibrations_and_maintenance(
    tmp_path, commissioned, store, new_store
):
    from ajtwin.cli.machine import machine

    reg = Registry(store)
    reg.add_machine("lab")
    reg.add_machine("other")  # its rows must not travel with "lab"
    save_calibration(reg, "other", commissioned, "other.parquet")
    save_calibration(reg, "lab", commissioned, "first.parquet")
    save_calibration(reg, "lab", commissioned, "second.parquet")  # newest = active
    record_maintenance(reg, "lab", nozzle_cleaned=True, vial_refilled_ml=1.2, note="weekly")
    record_maintenance(reg, "lab", reset_theta=True)
    before = _history(reg, "lab")
    assert before["active"]["source"] == "second.parquet"
    assert before["start"]["started_from"] == (
        f"commissioning {before['active']['id']} + maintenance"
    )
    assert before["start"]["start"][0][1] == 1.2  # the refill reached the next start
    # the standard errors and provenance are in the history
    assert before["calibrations"]["linewidth_gain_se"].iloc[0] == commissioned.std["linewidth_gain"]
    assert len(before["maintenance"]) == 2

    archive = tmp_path / "lab.tar"
    export_machine(reg, "lab", archive)
    target = new_store()
    fresh = Registry(target)
    assert import_machine(fresh, archive)["machine"] == "lab"
    imported = _history(fresh, "lab")
    # ids are renumbered: the start names the importing registry's calibration id
    assert imported["start"]["started_from"] == (
        f"commissioning {imported['active']['id']} + maintenance"
    )
    before_start = dict(before["start"], started_from=imported["start"]["started_from"])
    _assert_same(dict(before, start=before_start), imported)
    assert calibration_history(fresh, "lab")["source"].tolist() == [
        "first.parquet",
        "second.parquet",
    ]

    # the CLI's import under another name, next to the first copy
    res = CliRunner().invoke(
        machine, ["import", str(archive), "--as", "lab-2", "--store", str(target)]
    )
    assert res.exit_code == 0, res.output
    again = Registry(target)
    renamed = _history(again, "lab-2")
    renamed_start = dict(before["start"], started_from=renamed["start"]["started_from"])
    _assert_same(dict(before, start=renamed_start), renamed)
    assert len(calibration_history(again, "lab")) == 2  # the first copy is untouched

    # compact keeps them (and the start they give)
    compact(reg, "lab")
    _assert_same(before, _history(reg, "lab"))


def _schema3(store, drop_calibration_tables: bool):
    with Registry(store) as reg:
        if drop_calibration_tables:
            reg._db.execute("DROP TABLE calibrations")
            reg._db.execute("DROP TABLE maintenance_events")
        reg._db.execute("UPDATE info SET value = '3' WHERE key = 'schema_version'")


def test_schema3_registry_without_the_tables_migrates(store):
    reg = Registry(store)
    reg.add_machine("m")
    reg.close()
    _schema3(store, drop_calibration_tables=True)
    reg = Registry(store)
    # (later migrations follow these two: one message each)
    assert len(reg.migrated) == R.SCHEMA_VERSION - 3 and reg.migrated[:2] == [
        f"{store}: migrated registry schema 3 → 4 (per-machine calibrations and maintenance "
        "events)",
        f"{store}: migrated registry schema 4 → 5 (the detectors' long-run noise statistics per "
        "print and calibration)",
    ]
    assert CAL_TABLES <= reg._db.tables() and reg.machine("m")["name"] == "m"
    assert active_calibration(reg, "m") is None and maintenance_history(reg, "m").empty


def test_schema3_registry_whose_tables_calibration_py_created_keeps_its_rows(store, commissioned):
    reg = Registry(store)
    reg.add_machine("m")
    save_calibration(reg, "m", commissioned, "c.parquet")
    record_maintenance(reg, "m", vial_refilled_ml=0.8)
    before = _history(reg, "m")
    reg.close()
    _schema3(store, drop_calibration_tables=False)
    reg = Registry(store)
    assert len(reg.migrated) == R.SCHEMA_VERSION - 3
    assert "3 → 4" in reg.migrated[0] and "4 → 5" in reg.migrated[1]
    _assert_same(before, _history(reg, "m"))


def test_old_calibrations_table_without_noise_factors_gets_the_column(store, commissioned):
    # the first calibration tables had no noise_factors_json column
    reg = Registry(store)
    reg.add_machine("m")
    save_calibration(reg, "m", commissioned, "c.parquet")
    reg._db.execute("ALTER TABLE calibrations DROP COLUMN noise_factors_json")
    reg.close()
    _schema3(store, drop_calibration_tables=False)
    reg = Registry(store)
    active = active_calibration(reg, "m")
    assert active["noise_factors"] is None and active["source"] == "c.parquet"
    assert active["calibration"] == commissioned.calibration
