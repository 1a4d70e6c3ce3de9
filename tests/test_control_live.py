"""Closed-loop control of a live machine: the served virtual printer's stepping path and
``ajtwin control`` against it over OPC UA on loopback (127.0.0.1, free port, bounded waits)."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.live.opcua import SAMPLE_COLUMNS
from ajtwin.simulation import simulate


def _served(machine, stops) -> np.ndarray:
    for stop in stops:  # an irregular publishing rhythm, as the server's ticks give
        machine.rows(stop, 8)
    return machine.rows(machine.n_samples, machine.n_samples)


def test_served_print_without_writes_is_the_batch_print():
    from ajtwin.live.printer_server import VirtualMachine

    machine = VirtualMachine("m1", "exp1", seed=3, speed=30, duration_min=3)
    batch = simulate("exp1", 3, 3).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    served = _served(machine, [1, 2, 5, 9, 40, 41, 100, 170])
    assert served.shape == batch.shape == (180, len(SAMPLE_COLUMNS))
    assert np.array_equal(np.isnan(served), np.isnan(batch))
    np.testing.assert_allclose(served, batch, rtol=1e-12, atol=0.0)


def test_served_write_is_the_print_with_that_step():
    """A write at 64.3 s applies from 66 s: the batch print with that step in its schedule
    (what the server did before it stepped), the other inputs' schedule untouched."""
    from ajtwin.live.printer_server import VirtualMachine

    clog = {"fault": {"onset_min": 0.5}}
    machine = VirtualMachine("m1", "nozzle_clog", seed=2, speed=30, duration_min=3, overrides=clog)
    machine.rows(50, 8)
    assert machine.set_point("sheath_flow_sccm", 44.0, at_s=64.3) is None
    assert machine.set_point("carrier_flow_sccm", 80.0, at_s=70.0) is not None  # limits
    served = _served(machine, [70, 130])
    overrides = {"inputs": {"sheath_flow_sccm": [[0.0, 50.0], [66 / 60, 44.0]]}, **clog}
    batch = simulate("nozzle_clog", 2, 3, overrides).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    np.testing.assert_allclose(served, batch, rtol=1e-12, atol=0.0)
    assert machine.schedule == {"sheath_flow_sccm": [[66 / 60, 44.0]]}
    unchanged = simulate("nozzle_clog", 2, 3, clog).data[list(SAMPLE_COLUMNS)].to_numpy(float)
    np.testing.assert_array_equal(served[:66], unchanged[:66])  # the past stays
    assert np.nanmean(served[70:, 3]) == pytest.approx(44.0, abs=0.2)  # reported Q_s
    assert np.nanmean(unchanged[70:, 3]) == pytest.approx(50.0, abs=0.2)
