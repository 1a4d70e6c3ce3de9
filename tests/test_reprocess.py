"""``ajtwin reprocess``: the twin re-run over stored prints, in each machine's order, on
Dask; the results a new version beside the prints as stored."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.engine.ingest import ingest_record
from ajtwin.engine.reprocess import FIRST, plan, reprocess_print
from ajtwin.simulation import simulate
from ajtwin.store.registry import Registry, RegistryError


def _machine_prints(reg, name, seed, n=2, minutes=3.0):
    prev = None
    for k in range(n):
        rec = simulate("nozzle_clog" if k == n - 1 else "exp1", seed=seed + k,
                       duration_min=minutes, continue_from=prev,
                       overrides={"fault": {"onset_min": 1.0,
                                            "nozzle_deposition_multiplier": 2000.0}})  # fmt: skip
        ingest_record(reg, name, rec, source=f"{name}-{k}")
        prev = rec


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A registry of one machine with two ingested prints (the second with a clog)."""
    path = tmp_path_factory.mktemp("reprocess") / "lab.sqlite"
    reg = Registry(path)
    reg.add_machine("aj1")
    _machine_prints(reg, "aj1", seed=3)
    reg.close()
    return path


def test_a_reprocessing_with_nothing_changed_gives_the_stored_results(lab, store):
    from ajtwin.store.copy import copy_registry

    reg = Registry(store)
    copy_registry(Registry(lab), reg)  # the same prints, on SQLite or PostgreSQL
    version = reg.create_version("test", {})
    previous = FIRST
    for print_id in plan(reg).prints["aj1"]:
        previous = reprocess_print(reg, version, "aj1", print_id, previous)
    stored, again = reg.history("aj1"), reg.history("aj1", version=version)
    assert again["seq"].tolist() == [1, 2] and again["status"].tolist() == ["ok", "ok"]
    for column in stored.columns:
        assert stored[column].tolist() == again[column].tolist(), column  # bit for bit
    assert again["anomalies"].iloc[1] >= 1  # the clog, found again
    p1, v1 = reg.get_print(2), reg.print_version(version, 2, arrays=True)
    assert v1["summary"]["started_from"] == p1["summary"]["started_from"] == "print 1"
    assert np.array_equal(v1["end_cov"], p1["end_cov"])
    assert np.array_equal(v1["arrays"]["means"], reg.print_arrays(2)["means"])
    assert "measurements" not in v1["arrays"]  # the samples stay with the print
    # a resumed run does not write a print twice
    assert reprocess_print(reg, version, "aj1", 1, FIRST).seconds == 0.0
    assert reg.versions()[-1]["n_prints"] == 2


def test_a_model_change_reprocessed_on_dask_is_a_new_version_beside_the_old(lab, pg_store):
    from ajtwin.engine.reprocess import reprocess
    from ajtwin.store.copy import copy_registry

    reg = Registry(pg_store)
    copy_registry(Registry(lab), reg)
    reg.add_machine("aj2")
    reg.close()
    with Registry(lab) as src:
        before = src.history("aj1")
    done = reprocess(pg_store, workers=2, reason="θ no longer learned",
                     settings={"twin_overrides": {"em": False}})  # fmt: skip
    assert (done["version"], done["prints"], done["machines"], done["workers"]) == (2, 2, 1, 2)
    reg = Registry(pg_store)
    assert [(v["id"], v["status"], v["n_prints"]) for v in reg.versions()] == [
        (1, "done", 2),
        (2, "done", 2),
    ]
    stored, new = reg.history("aj1"), reg.history("aj1", version=2)
    assert stored.equals(before)  # nothing overwritten
    assert (new["theta_nozzle_deposition_um"] == 0).all()  # the new model's results
    assert not np.allclose(new["end_nozzle_deposition_um"], stored["end_nozzle_deposition_um"])
    res = CliRunner().invoke(main, ["machine", "history", "aj1", "--version", "2", "--store",
                                    pg_store])  # fmt: skip
    assert res.exit_code == 0 and res.output.count("\n") >= 3, res.output
    res = CliRunner().invoke(main, ["machine", "history", "aj1", "--version", "9", "--store",
                                    pg_store])  # fmt: skip
    assert res.exit_code == 1 and "no version 9 of results (known: 1, 2)" in res.output


def test_a_reprocessing_from_a_date_starts_from_the_stored_chain(lab, tmp_path):
    import shutil

    path = tmp_path / "lab.sqlite"
    shutil.copy(lab, path)
    reg = Registry(path)
    second = reg.get_print(2)
    reg._db.execute("UPDATE prints SET ingested_at = '2020-01-01T00:00:00+00:00' WHERE seq = 1")
    work = plan(reg, ["aj1"], since="2021-01-01")
    assert work.prints == {"aj1": [2]}
    carry = work.first_carry["aj1"]
    assert carry.from_seq == 1 and np.array_equal(carry.theta, reg.get_print(1)["theta_after"])
    version = reg.create_version("since", {})
    reprocess_print(reg, version, "aj1", 2, carry)
    again = reg.print_version(version, 2)
    assert np.array_equal(again["end_mean"], second["end_mean"])
    with pytest.raises(RegistryError, match="no machine 'ghost'"):
        plan(reg, ["ghost"])


def test_a_cluster_cannot_share_an_sqlite_registry(lab):
    res = CliRunner().invoke(main, ["reprocess", "--scheduler", "tcp://127.0.0.1:1",
                                    "--store", str(lab), "--no-progress"])  # fmt: skip
    assert res.exit_code == 1 and "cannot share the SQLite file" in res.output, res.output
