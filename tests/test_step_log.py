"""The bounded per-step logs of the detectors and the live stream: addressed by step number,
the oldest dropped, never more than an eighth beyond what they keep."""

from __future__ import annotations

import pytest

from ajtwin.apps.detection.steplog import StepLog


def test_a_step_log_holds_at_most_an_eighth_more_steps_than_it_keeps():
    log = StepLog(keep=800)
    held = []
    for k in range(10_000):
        log.append(float(k))
        held.append(len(log.kept()))
    assert max(held) <= 900
    assert min(held[800:]) >= 800
    assert len(log) == 10_000
    assert log[9_999] == 9_999.0 and log[9_200] == 9_200.0
    assert log[9_500:9_503] == [9_500.0, 9_501.0, 9_502.0]
    with pytest.raises(IndexError, match="not kept"):
        log[log.first - 1]


def test_a_step_log_without_a_bound_keeps_every_step():
    log = StepLog()
    for k in range(5_000):
        log.append(k)
    assert log.first == 0 and log.kept() == list(range(5_000))
