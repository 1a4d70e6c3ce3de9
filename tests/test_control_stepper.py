"""The stepped virtual printer (closed-loop simulation) against the batch printer."""

from __future__ import annotations

import numpy as np
import pytest

from ajtwin.simulation import run_virtual_print
from ajtwin.simulation.stepper import SteppedPrinter


def _frame(record):
    return record.data.to_numpy(dtype=float)


def test_stepping_without_changes_is_the_batch_print():
    batch = run_virtual_print("exp3", seed=2, duration_min=8.05)
    printer = SteppedPrinter("exp3", seed=2, duration_min=8.05)
    while not printer.done:
        printer.advance(10)  # 483 s: the last chunk is padded and trimmed
    a, b = _frame(batch.record), _frame(printer.record())
    assert np.array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(printer.true_outputs, batch.outputs_true, rtol=1e-12)


def test_a_command_equals_the_same_step_in_the_schedule():
    """A set-point change at 5 min gives the print whose schedule had that step."""
    overrides = {"inputs": {"carrier_flow_sccm": [[0.0, 23.0], [5.0, 25.0]]}}
    clog = {"fault": {"onset_min": 2.0}}  # a fault in the print, too
    batch = run_virtual_print(
        "nozzle_clog", seed=4, duration_min=9, overrides={**overrides, **clog}
    )
    printer = SteppedPrinter("nozzle_clog", seed=4, duration_min=9, overrides=clog)
    for _ in range(30):
        printer.advance(10)
    printer.set_setpoints([375.0, 25.0, 50.0])
    while not printer.done:
        printer.advance(10)
    np.testing.assert_allclose(_frame(printer.record()), _frame(batch.record), rtol=1e-12)


def test_past_is_unchanged_by_a_later_command():
    """Causality: what was printed before a command does not depend on it."""
    a = SteppedPrinter("exp1", seed=1, duration_min=4)
    b = SteppedPrinter("exp1", seed=1, duration_min=4)
    chunk_a = [a.advance(10) for _ in range(12)]
    chunk_b = [b.advance(10) for _ in range(12)]
    b.set_setpoints([400.0, 27.0, 45.0])
    later_b = b.advance(10)
    later_a = a.advance(10)
    for _ in range(11):
        later_b, later_a = b.advance(10), a.advance(10)  # the last 10 s of 4 min
    for ca, cb in zip(chunk_a, chunk_b):
        np.testing.assert_array_equal(ca.outputs, cb.outputs)
    # the command moves the carrier flow the MFC reports and the line
    assert np.mean(later_b.inputs[:, 1]) - np.mean(later_a.inputs[:, 1]) == pytest.approx(
        4.0, abs=0.2
    )
    assert np.mean(later_b.true_outputs[:, 0]) > np.mean(later_a.true_outputs[:, 0]) + 5


def test_stepper_rejects_bad_use():
    printer = SteppedPrinter("exp1", seed=0, duration_min=0.5)
    with pytest.raises(ValueError, match="atomizer_current_mA"):
        printer.set_setpoints([np.nan, 23.0, 50.0])
    with pytest.raises(ValueError, match="at least 1 s"):
        printer.advance(0)
    for _ in range(3):
        printer.advance(10)
    assert printer.done and len(printer.true_outputs) == 30
    with pytest.raises(RuntimeError, match="over"):
        printer.advance(1)


def test_alt_truth_stepping_is_the_batch_alt_print_and_takes_commands():
    """The second truth generator in the loop: stepping without commands gives
    ``simulate --truth alt``'s print; a command equals that step in the schedule."""
    batch = run_virtual_print("exp3", seed=2, duration_min=6.05, truth_generator="alt")
    printer = SteppedPrinter("exp3", seed=2, duration_min=6.05, truth="alt")
    while not printer.done:
        printer.advance(10)
    a, b = _frame(batch.record), _frame(printer.record())
    assert np.array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=0.0)
    assert printer.record().meta["truth_generator"] == "alt"
    # not the first generator's print (same seed): the generator really is swapped
    first = run_virtual_print("exp3", seed=2, duration_min=6.05)
    assert np.max(np.abs(first.states[:, 0] - batch.states[:, 0])) > 0.01

    overrides = {"inputs": {"carrier_flow_sccm": [[0.0, 23.0], [3.0, 25.0]]}}
    stepped = run_virtual_print(
        "exp1", seed=4, duration_min=6, overrides=overrides, truth_generator="alt"
    )
    printer = SteppedPrinter("exp1", seed=4, duration_min=6, truth="alt")
    for _ in range(18):
        printer.advance(10)
    printer.set_setpoints([375.0, 25.0, 50.0])
    while not printer.done:
        printer.advance(10)
    np.testing.assert_allclose(_frame(printer.record()), _frame(stepped.record), rtol=1e-12)
    with pytest.raises(ValueError, match="truth generator"):
        SteppedPrinter("exp1", seed=1, truth="other")
