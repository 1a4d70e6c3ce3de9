"""Long runs: a long virtual print through the twin, and many prints of one
machine through the registry. Small instances run by default; a day, a week and a year
of daily prints behind ``slow`` (figures in docs/validation.md)."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.studies.soak import covariance_health, memory_mb, soak_machine, soak_print


def test_covariance_health_catches_what_it_should():
    good = np.tile(np.diag([1e-2, 1e-6, 1e-10, 1e-6, 1e-16]), (3, 1, 1))
    assert covariance_health(good)["min_corr_eig"] == pytest.approx(1.0)
    asym = good.copy()
    asym[1, 0, 1] = 0.5 * np.sqrt(1e-2 * 1e-6)  # correlation 0.5 one way only
    assert covariance_health(asym)["max_asymmetry"] == pytest.approx(0.5)
    indefinite = good.copy()
    c = 1.5 * np.sqrt(1e-2 * 1e-6)  # |correlation| > 1: not a covariance
    indefinite[2, 0, 1] = indefinite[2, 1, 0] = c
    assert covariance_health(indefinite)["min_corr_eig"] == pytest.approx(-0.5)
    nan = good.copy()
    nan[0, 2, 2] = np.nan
    assert not covariance_health(nan)["finite"]
    rss, hwm = memory_mb()
    assert 0 < rss <= hwm


def _check_print_soak(rep, hours):
    table = rep.table()
    assert table["hour_end"].iloc[-1] == pytest.approx(hours)
    assert rep.healthy, table.to_string()
    # a clean print: the divergence guard never has a reason to fire
    assert rep.guard_firings == 0, rep.guard_steps[:10]
    assert (table["max_theta_over_prior"] < 5).all()  # θ stays near its prior, no run-away
    # the twin keeps tracking the truth: vial within 0.01 mL, nozzle deposit within 0.02 µm
    assert (np.abs(table["end_1"] - table["true_1"]) < 0.01).all()
    assert (np.abs(table["end_3"] - table["true_3"]) < 0.02).all()
    # memory flat once warm: the chunks' results are not kept
    assert table["hwm_mb"].iloc[-1] - table["hwm_mb"].iloc[1] < 100
    return table


def test_two_hour_print_through_the_twin():
    rep = soak_print(hours=2.0, chunk_min=60.0, seed=4)
    _check_print_soak(rep, 2.0)


@pytest.mark.slow
def test_day_long_print_through_the_twin():
    rep = soak_print(hours=24.0, chunk_min=60.0, seed=5)
    _check_print_soak(rep, 24.0)


@pytest.mark.slow
def test_week_long_print_through_the_twin():
    rep = soak_print(hours=24.0 * 7, chunk_min=60.0, seed=6)
    table = rep.table()
    assert rep.healthy and rep.guard_firings == 0
    assert (table["max_theta_over_prior"] < 5).all()
    assert (np.abs(table["end_1"] - table["true_1"]) < 0.02).all()
    assert table["hwm_mb"].iloc[-1] - table["hwm_mb"].iloc[1] < 100


def _check_machine_soak(table, n, vial_tol_ml=0.01):
    assert len(table) == n and (table["status"] == "ok").all()
    assert table["started_from"].tolist() == ["initial fit"] + [f"print {k}" for k in range(1, n)]
    # the twin follows the machine over its life: vial and nozzle deposit at every print's end
    assert (np.abs(table["end_1"] - table["true_1"]) < vial_tol_ml).all()
    assert (np.abs(table["end_3"] - table["true_3"]) < 0.02).all()
    theta = table[[f"theta_{k}" for k in range(5)]].to_numpy()
    from ajtwin.estimation import Twin

    prior = np.asarray(Twin.default().config.theta_prior_std, dtype=float)
    assert np.all(np.isfinite(theta)) and np.all(np.abs(theta) / prior < 5)


@pytest.fixture(scope="module")
def twenty_prints(tmp_path_factory):
    store = tmp_path_factory.mktemp("soak") / "r.sqlite"
    # a 60-s EM window so that θ is learned within 2-min prints and carried over
    overrides = {"window_s": 60, "every_s": 30}
    return store, soak_machine(20, print_min=2.0, store=store, seed=30, twin_overrides=overrides)


def test_machine_many_prints_carry_over_exactly(twenty_prints):
    """20 prints of one machine: each starts exactly (bit for bit) from the previous end
    and θ; the registry adds no numerical drift; history and show use indexes."""
    from ajtwin.engine.chain import carry_over
    from ajtwin.store.registry import Registry

    store, table = twenty_prints
    n = len(table)
    _check_machine_soak(table, n)
    reg = Registry(store)
    prints = [reg.print_by_seq("soak", k) for k in range(1, n + 1)]
    assert np.any(table[[f"theta_{k}" for k in range(5)]].to_numpy() != 0)  # θ is learned
    for before, after in zip(prints, prints[1:]):
        mean, cov = carry_over(before["end_mean"], before["end_cov"])
        assert np.array_equal(after["start_mean"], mean)
        assert np.array_equal(after["start_cov"], cov)
        assert np.array_equal(after["theta_before"], before["theta_after"])
    assert len(reg.history("soak")) == n
    # the queries of history/show/the chain search by index, never scan a table
    machine_id = reg.machine("soak")["id"]
    for query, args in (
        ("SELECT * FROM prints WHERE machine_id = ? AND status = 'ok' ORDER BY seq DESC "
         "LIMIT 1", (machine_id,)),
        ("SELECT COUNT(*) FROM prints WHERE machine_id = ?", (machine_id,)),
        ("SELECT p.*, (SELECT COUNT(*) FROM anomalies a WHERE a.print_id = p.id) FROM prints p "
         "WHERE machine_id = ? ORDER BY seq", (machine_id,)),
        ("SELECT p.seq FROM anomalies a JOIN prints p ON a.print_id = p.id WHERE "
         "p.machine_id = ?", (machine_id,)),
        ("SELECT name, npy FROM print_arrays WHERE print_id = ?", (1,)),
    ):  # fmt: skip
        plan = " | ".join(r[3] for r in reg._db.execute("EXPLAIN QUERY PLAN " + query, args))
        assert "SCAN" not in plan.replace("SCAN CONSTANT ROW", ""), (query, plan)


def _vial_within_band(store, table, k_sigma=3.0):
    from ajtwin.store.registry import Registry

    reg = Registry(store)
    sd = np.array([np.sqrt(reg.print_by_seq("soak", k)["end_cov"][1, 1]) for k in table["seq"]])
    return np.abs(table["end_1"] - table["true_1"]).to_numpy() < k_sigma * sd


def test_machine_vial_band_covers_the_truth(twenty_prints):
    """The vial over 20 short prints: the truth inside ±3σ at every print's end."""
    assert _vial_within_band(*twenty_prints).all()


@pytest.fixture(scope="module")
def year_of_prints(tmp_path_factory):
    store = tmp_path_factory.mktemp("year") / "year.sqlite"
    return store, soak_machine(365, print_min=3.0, store=store, seed=1000)


@pytest.mark.slow
def test_machine_year_of_daily_prints(year_of_prints):
    _, table = year_of_prints
    # vial: 0.02 mL (2 % of the vial): the estimator's V_l bias over many short prints
    # reached 0.014 mL in this run before V_l became a consider state
    _check_machine_soak(table, 365, vial_tol_ml=0.02)


@pytest.mark.slow
def test_machine_year_vial_band_covers_the_truth(year_of_prints):
    # was a strict xfail: the vial estimate, updated from the generation signature, stayed
    # near 1 mL with σ ~0.7 µL while the truth emptied; V_l is a consider state, so its band
    # is the fill's σ carried from print to print
    assert _vial_within_band(*year_of_prints).all()
