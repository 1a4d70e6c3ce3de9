"""A live print's part map fed from the live engine (wiring: engine → the quality app).

:func:`follow_engine` subscribes a :class:`~ajtwin.apps.quality.live_map.LivePartMap` to a
machine's committed steps and hands each new piece of the map to the page's publisher.
"""

from __future__ import annotations

from ajtwin.apps.quality.live_map import LivePartMap
from ajtwin.engine.messages import StepMessage


def follow_engine(engine, machine: str, part: LivePartMap, publish) -> callable:
    """Feed ``part`` from a live engine's committed steps of ``machine``; each chunk goes to
    ``publish(machine, chunk)``. Returns the function that stops it.

    Only committed steps are used (on a job print: final ones, H seconds after they were
    printed; provisional messages are skipped), each with the covariance the twin reports
    (:attr:`~ajtwin.engine.messages.StepMessage.covariance`). The line model is the
    machine's own twin's (its calibration), taken from its stream at the first step.
    """

    def on_message(message):
        if not isinstance(message, StepMessage) or message.machine != machine:
            return
        if message.provisional:
            return
        if part.line_model is None:
            stream = engine.stream(machine)
            if stream is None:
                return
            part.line_model = stream.twin.line_model
        chunk = part.step(message.time_s, message.mean, message.covariance, message.input_values)
        alarms = message.raised()
        if alarms:
            chunk = dict(chunk or {})
            chunk["alarms"] = part.alarms(alarms)
        if chunk:
            publish(machine, chunk)

    return engine.subscribe(on_message)
