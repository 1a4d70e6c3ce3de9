"""The mismatch guard taken a chunk at a time gives the whole-print guard's verdict."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.apps.detection.mismatch import (
    ChunkedGuard,
    assess,
    assess_run,
    first_em_update_s,
    load_guard_settings,
)
from ajtwin.engine.ingest import ingest_record
from ajtwin.estimation.twin import Twin, first_em_update_time
from ajtwin.simulation.machine import MachineDeviation
from ajtwin.simulation.printer import simulate
from ajtwin.store.registry import Registry

NOMINAL = np.array([3.5, 1.0, 0.0, 0.01, 4.6e-7])


def _print(n: int, seed: int = 3):
    """A print of ``n`` s whose innovations drift in and out of a bias around several
    chunk boundaries, with a noisy NIS, logger gaps, a deposit dipping below zero and a
    start-window jump: every test of the guard has something to find."""
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.arange(n, dtype=float)
    e = rng.normal(0.0, 1.0, (n, 5))
    # a slow bias on P_c and Q_m, crossing the threshold a few times within windows
    e[:, 2] += 1.1 * np.sin(2 * np.pi * np.arange(n) / 1700.0)
    e[:, 4] += 0.9 * np.cos(2 * np.pi * np.arange(n) / 1300.0)
    e[:, 1] += 0.7 * (np.arange(n) % 2300 > 1500)
    e[rng.random((n, 5)) < 0.2] = np.nan  # not measured
    e[2000:2700, :] = np.nan  # a logger gap
    n_measured = np.isfinite(e).sum(axis=1).astype(float)
    nis = np.nansum(e**2, axis=1) * (1.0 + 2.5 * (np.arange(n) % 3100 > 2400))
    means = np.tile(NOMINAL, (n, 1))
    stds = np.full((n, 5), 1e-3)
    means[:, 4] = -0.004 - 0.004 * (np.arange(n) % 2900 > 2600)  # below zero, now and then
    means[40:90, 3] = 0.5  # moves far within the start window
    return t, means, e, nis, n_measured, stds


def _chunked(inputs, chunk: int, **kwargs):
    guard = ChunkedGuard(**kwargs)
    n = len(inputs[0])
    for k in range(0, n, chunk):
        guard.add(*(a[k : k + chunk] for a in inputs))
    return guard.finish()


@pytest.mark.parametrize("learned", [None, 1120.0, 1900.0])
@pytest.mark.parametrize("chunk", [300, 457])
def test_chunked_guard_gives_the_whole_print_verdict_and_flags(chunk, learned):
    inputs = _print(9000)
    start = dict(start_mean=NOMINAL, start_cov=np.diag((0.05 * NOMINAL + 1e-3) ** 2))
    whole = assess(*inputs[:5], stds=inputs[5], level_learned_s=learned, **start)
    chunked = _chunked(inputs, chunk, level_learned_s=learned, **start)
    assert whole.mismatch and len(whole.reasons) >= 5  # the print has findings to keep
    assert chunked.to_dict() == whole.to_dict()
    np.testing.assert_array_equal(chunked.flags, whole.flags)


def test_chunked_guard_carries_its_windows_over_chunk_boundaries():
    """Judged without the rows before each chunk, the rolling windows would restart at each
    boundary and flag other seconds: the carried-over rows are what makes them equal."""
    inputs = _print(9000)
    whole = assess(*inputs[:5], stds=inputs[5])
    g = load_guard_settings()
    chunked = _chunked(inputs, 300, settings=g)
    np.testing.assert_array_equal(chunked.flags, whole.flags)
    # the same print judged as separate pieces (nothing carried) differs
    pieces = [assess(*(a[k : k + 300] for a in inputs[:5]), stds=inputs[5][k : k + 300],
                     settings=g) for k in range(0, 9000, 300)]  # fmt: skip
    assert not np.array_equal(np.concatenate([p.flags for p in pieces]), whole.flags)


def test_chunked_guard_judges_a_short_print_nis_at_its_end():
    """A print shorter than the NIS window has its NIS judged over the print so far at
    its last second, whatever the chunks."""
    n = 200
    t = np.arange(n, dtype=float)
    e = np.zeros((n, 5))
    nis = np.full(n, 40.0)  # far from 1 per output
    inputs = (t, np.tile(NOMINAL, (n, 1)), e, nis, np.full(n, 5.0))
    whole = assess(*inputs)
    chunked = _chunked(inputs, 70)
    assert whole.mismatch and "nis" in whole.message.lower()
    assert chunked.to_dict() == whole.to_dict()
    np.testing.assert_array_equal(chunked.flags, whole.flags)


def test_ingest_stores_the_whole_run_guard_verdict(tmp_path):
    """Ingest judges each chunk as the twin gives it (EM's boundaries, its first update
    known before the run): the stored verdict is the whole run's."""
    gauges = MachineDeviation(name="gauge+8%", carrier_gauge_gain=1.08, sheath_gauge_gain=1.08)
    record = simulate("exp1", seed=303, duration_min=16.0, machine=gauges)
    reg = Registry(tmp_path / "r.sqlite")
    reg.add_machine("m")
    result = ingest_record(reg, "m", record, keep_run=True)
    whole = assess_run(result.run, record).to_dict()
    assert whole["mismatch"]
    assert result.summary["mismatch"] == whole


@pytest.mark.parametrize(
    "config",
    [
        {},  # the default schedule: an early update at 120 s
        {"early_em_s": ()},  # the first update at window_s
        {"early_em_s": (45, 200), "every_s": 150, "window_s": 300},
    ],
)
def test_ems_first_update_is_known_before_the_run_as_the_run_makes_it(config):
    """The chunked guard is told before the run when EM's first update takes effect: the
    time predicted from the twin's config is the one the run's θ history then shows."""
    record = simulate("exp1", seed=11, duration_min=12.0)
    twin = Twin.default(**config)
    predicted = first_em_update_time(twin.config, record.time_s)
    run = twin.run(record)
    assert predicted is not None
    assert predicted == first_em_update_s(run)
