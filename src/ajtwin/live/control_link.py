"""Closed-loop control of a live machine over OPC UA (``ajtwin control --machine … --opcua …``).

:class:`ControlLink` talks to the server and nothing else. It follows one machine the way
``ajtwin live`` does (the login, security and refusal handling of
:class:`ajtwin.live.link.OpcUaLink`; the ``SampleBuffer`` subscription; every buffer through
:func:`ajtwin.live.link.buffer_samples`), hands the samples to the controlled print
(:class:`ajtwin.engine.control.ControlledPrint`: the machine's twin, the MPC on it — the very
controller ``ajtwin control simulate`` runs against the virtual printer — and the
supervisor's rules, :class:`ajtwin.apps.planning.supervisor.Supervisor`) and writes what it
decides to the three writable set-point nodes (docs/reference/opcua.md):

* the command in force is read back from the set-point nodes before each decision (an
  operator's change or a refused write is what the controller starts from), and the
  machine's clock is read so that two periods' moves never bunch;
* the limits are intersected with the nodes' ``EURange``;
* writing needs an authenticated session: at the start the set-points in force are
  written back unchanged, so a refusal stops the link with a clear message before any
  control (``LinkRefused``); a refused login or certificate likewise.

Network faults are retried with back-off; the twin keeps its state across a reconnection
(the samples the server no longer buffers are a gap = missing data). The link ends when
the machine's ``PrintState`` says ``finished`` (or ``stop`` is set).
"""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
from asyncua import ua

from ajtwin.apps.planning.mpc import TargetError
from ajtwin.apps.planning.supervisor import ControlDecision, ControlTarget
from ajtwin.engine.control import CameraOnJob, ControlledPrint
from ajtwin.live.link import LinkRefused, OpcUaLink, OpcUaLogin, _refusal, buffer_samples
from ajtwin.live.opcua import NAMESPACE_URI, SAMPLE_WIDTH, SETPOINTS, node_path

log = logging.getLogger("ajtwin.control")

WRITE_REFUSED = (
    "the server refused the set-point write ({code}): set-points may be written only by an "
    "authenticated user; give --username/--password (and --security on an encrypted server)"
)


class ControlLink:
    """Control one machine on an OPC UA server (see module docstring).

    Parameters
    ----------
    url : str
        ``opc.tcp://host:port``.
    machine : str
    target : ControlTarget
        The target linewidth, the machine's limits (intersected with the set-point nodes'
        ``EURange``), the controller's settings, the vial's fill.
    login : OpcUaLogin, optional
        As for :class:`~ajtwin.live.link.OpcUaLink`.
    job : ajtwin.job.Job, optional
        The program the machine prints (read with its speeds; run again over the same part
        when it ends).
    camera : CameraOnJob, optional
        The machine's camera on a job print.
    engine : ajtwin.engine.fleet.LiveEngine, optional
        The machine's twin is the engine's (its print stored in the engine's registry with
        the job, every step published to its subscribers); default the controller's own.
    on_decision : callable, optional
        Called with each :class:`~ajtwin.apps.planning.supervisor.ControlDecision`.
    max_backoff_s : float
        Longest wait between reconnection attempts.
    publish_ms : int
        Subscription publishing interval.
    """

    def __init__(
        self,
        url: str,
        machine: str,
        target: ControlTarget,
        *,
        login: OpcUaLogin | None = None,
        job=None,
        camera: CameraOnJob | None = None,
        engine=None,
        on_decision=None,
        max_backoff_s: float = 10.0,
        publish_ms: int = 100,
    ):
        self.url, self.machine = url, machine
        self.max_backoff_s = float(max_backoff_s)
        self.publish_ms = int(publish_ms)
        self.on_decision = on_decision
        # the client side of `ajtwin live` (login, security, certificates), no engine
        self._login = OpcUaLink(url, [machine], engine=None, login=login)
        self.print = ControlledPrint(machine, target, job=job, camera=camera, engine=engine)
        self.decisions: list[ControlDecision] = []
        self.finished = False
        self.print_id = None  # the engine's stored print, once finished

    @property
    def controller(self):
        """The MPC on the twin (None until :meth:`prepare`)."""
        return self.print.controller

    def prepare(self) -> None:
        """Build the twin and the MPC (and compile them); done on the first connection
        unless called before (a test calls it before the server's clock starts)."""
        self.print.prepare()

    # ------------------------------------------------------------------ running
    async def run(self, stop: asyncio.Event | None = None) -> list[ControlDecision]:
        """Control until the print is finished (or ``stop`` is set); the decisions."""
        try:
            await self._run(stop)
        finally:
            if self.finished and self.print.controller is not None:
                # the print with its job, stored as an ordinary registry print
                self.print_id = self.print.close()
        return self.decisions

    async def _run(self, stop):
        backoff = 0.5
        while (stop is None or not stop.is_set()) and not self.finished:
            try:
                await self._session(stop)
                backoff = 0.5
            except (LinkRefused, TargetError, AssertionError):
                raise  # retrying cannot help; a broken limit must stop the controller
            except (asyncio.CancelledError, KeyboardInterrupt):
                raise
            except Exception as exc:  # network faults, server restarts: retry
                refusal = _refusal(exc)
                if refusal:
                    raise LinkRefused(f"{self.url}: {refusal} ({type(exc).__name__})") from None
                log.warning(
                    "%s: disconnected (%s: %s); reconnecting in %g s; the machine keeps "
                    "its set-points",
                    self.url,
                    type(exc).__name__,
                    exc,
                    backoff,
                )
                try:
                    await asyncio.wait_for(
                        stop.wait() if stop else asyncio.sleep(backoff), timeout=backoff
                    )
                except TimeoutError:
                    pass
                backoff = min(2 * backoff, self.max_backoff_s)

    async def _session(self, stop):

        client = await self._login._client()
        self._client = client
        async with client:
            idx = await client.get_namespace_index(NAMESPACE_URI)

            def node(*parts):
                return client.get_node(ua.NodeId(node_path(self.machine, *parts), idx))

            buffer = node("Monitoring", "Process", "SampleBuffer")
            state = node("Monitoring", "Process", "PrintState")
            self._clock = node("Monitoring", "Process", "SampleTime")
            setpoints = {
                column: node("Monitoring", "SetPoints", key)
                for key, (column, *_) in SETPOINTS.items()
            }
            try:
                await buffer.read_browse_name()
            except ua.UaStatusCodeError as exc:
                raise LinkRefused(
                    f"{self.url}: machine {self.machine!r} is not served ({exc})"
                ) from None
            ranges = {}
            for key, (column, *_) in SETPOINTS.items():
                try:
                    rng = await node("Monitoring", "SetPoints", key, "EURange").read_value()
                    ranges[column] = (float(rng.Low), float(rng.High))
                except ua.UaStatusCodeError:
                    pass  # no EURange: the registry's limits alone
            u = await self._read_setpoints(setpoints)
            await self._write(setpoints, dict(zip(setpoints, u)), probe=True)
            if self.print.controller is None:  # compiled once we know we may write
                log.warning("%s: compiling the twin and the MPC …", self.machine)
                await asyncio.get_running_loop().run_in_executor(None, self.prepare)
            try:
                if self.print.supervisor.narrow_limits(ranges):
                    log.info(
                        "%s: limits narrowed to the server's EURange: %s",
                        self.machine,
                        self.print.supervisor.limits,
                    )
            except ValueError as exc:
                raise LinkRefused(f"{self.url}: {self.machine} {exc}") from None
            queue: asyncio.Queue = asyncio.Queue()

            class Handler:
                def datachange_notification(self, n, value, data):
                    queue.put_nowait((n.nodeid, value))

                def status_change_notification(self, status):
                    queue.put_nowait(("status", status))

            sub = await client.create_subscription(self.publish_ms, Handler())
            await sub.subscribe_data_change([buffer, state])
            target = self.print.target.target_um
            log.info("%s: controlling %s to L_w = %g µm", self.url, self.machine, target)
            print_state = "printing"
            last_check = time.monotonic()
            while stop is None or not stop.is_set():
                try:
                    batch = [await asyncio.wait_for(queue.get(), timeout=0.5)]
                except TimeoutError:
                    batch = []
                while not queue.empty():
                    batch.append(queue.get_nowait())
                latest = None
                for nodeid, value in batch:
                    if nodeid == "status":
                        raise ConnectionError(f"subscription status {value}")
                    if nodeid == state.nodeid:
                        print_state = str(value)
                    elif nodeid == buffer.nodeid:
                        latest = value
                fed = self._feed(latest) if latest is not None else 0
                if print_state == "finished" and latest is None:
                    self.finished = True
                    return
                if fed and self.print.due:
                    await self._decide(setpoints)
                if time.monotonic() - last_check > 2.0:
                    await client.check_connection()
                    last_check = time.monotonic()

    def _feed(self, value) -> int:
        """New rows of the SampleBuffer → the controlled print; how many samples were fed."""
        try:  # the buffer's NaN padding (docs/reference/opcua.md) is not a problem worth a log line
            rows = np.asarray(value, dtype=float).reshape(-1, SAMPLE_WIDTH)
            value = rows[~np.all(np.isnan(rows), axis=1)]
        except (TypeError, ValueError, OverflowError):
            pass  # buffer_samples refuses it with a log line
        samples, _, problems = buffer_samples(self.machine, value, self.print.last_time)
        for p in problems:
            log.warning(p)
        return self.print.feed(samples)

    async def _read_setpoints(self, setpoints) -> np.ndarray:
        return np.array([float(await n.read_value()) for n in setpoints.values()])

    async def _decide(self, setpoints) -> None:
        machine_now = float(await self._clock.read_value())
        u = await self._read_setpoints(setpoints)
        decision = await asyncio.get_running_loop().run_in_executor(
            None, self.print.decide, u, machine_now
        )
        if decision is None:  # a period of the machine's clock has not passed
            return
        if decision.written:
            await self._write(setpoints, decision.written)
            self.print.supervisor.written(float(await self._clock.read_value()))
        self.decisions.append(decision)
        if decision.status in ("hold", "stop"):  # stop: latched, the ink ran low
            log.warning(
                "%s t = %.0f s: %s — %s",
                self.machine,
                decision.time_s,
                decision.status.upper(),
                decision.reason,
            )
        if self.on_decision:
            self.on_decision(decision)

    async def _write(self, setpoints, values: dict, probe: bool = False) -> None:

        for column, value in values.items():
            if not probe:  # the probe writes back the machine's own values
                low, high = self.print.supervisor.limits[column]
                assert low <= value <= high, f"{column} = {value} outside [{low}, {high}]"
        nodes = [setpoints[column] for column in values]
        data = [ua.DataValue(ua.Variant(float(v), ua.VariantType.Double)) for v in values.values()]
        try:  # one request: the machine takes the three together
            results = await self._client.write_values(nodes, data, raise_on_partial_error=False)
        except ua.UaStatusCodeError as exc:
            results = [exc]
        for column, result in zip(values, results):
            code = type(result).__name__ if isinstance(result, Exception) else result.name
            if code in ("BadUserAccessDenied", "BadNotWritable", "BadWriteNotSupported"):
                what = "checking write access" if probe else f"writing {column}"
                raise LinkRefused(
                    f"{self.url}: {self.machine}: {WRITE_REFUSED.format(code=code)} (while {what})"
                )
            if isinstance(result, Exception):
                raise result
            if not result.is_good():
                log.warning("%s: writing %s refused by the server: %s", self.machine, column, code)


__all__ = ["ControlDecision", "ControlLink", "LinkRefused", "OpcUaLogin"]
