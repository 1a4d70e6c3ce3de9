"""Closed-loop control of a live machine over OPC UA (``ajtwin control --machine … --opcua …``).

:class:`ControlLink` follows one machine the way ``ajtwin live`` does (the login, security
and refusal handling of :class:`ajtwin.live.link.OpcUaLink`; the ``SampleBuffer``
subscription; every buffer through :func:`ajtwin.live.link.buffer_samples`), feeds the
samples to the streaming twin (:class:`ajtwin.engine.stream.TwinStream`, inside
:class:`ajtwin.engine.control.MPCTwin` — the very controller ``ajtwin control simulate``
runs against the virtual printer) and, every ``period_s`` seconds of print, writes the
MPC's command to the three writable set-point nodes (docs/reference/opcua.md):

* the command in force is read back from the set-point nodes before each decision (an
  operator's change or a refused write is what the controller starts from);
* every command passes :func:`ajtwin.apps.planning.mpc.clip_command`: inside the machine's
  limits (registry ∩ the nodes' ``EURange`` ∩ the validity range of the fit) and within
  the rate limits × the print time since the last write;
* no write during the warm-up, while the twin reports a model–machine mismatch or an
  alarm it cannot act on (the reasons are logged; the machine keeps what it has);
* the target is checked when the twin has its first state: unreachable within the limits
  from that state → :class:`~ajtwin.apps.planning.mpc.TargetError` naming the reachable range;
* writing needs an authenticated session: at the start the set-points in force are
  written back unchanged, so a refusal stops the link with a clear message before any
  control (``LinkRefused``); a refused login or certificate likewise.

Network faults are retried with back-off; the twin keeps its state across a reconnection
(the samples the server no longer buffers are a gap = missing data). The link ends when
the machine's ``PrintState`` says ``finished`` (or ``stop`` is set).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from dataclasses import dataclass, field

import numpy as np
from asyncua import ua

from ajtwin.apps.planning.advice import effective_bounds
from ajtwin.apps.planning.mpc import (
    ControlSettings,
    TargetError,
    check_target,
    clip_command,
    reachable_linewidth,
)
from ajtwin.apps.planning.strategies import Decision
from ajtwin.engine.control import MPCTwin
from ajtwin.engine.job_samples import JobColumns, live_loop
from ajtwin.estimation import Twin
from ajtwin.estimation.print_time import PrintContext, camera_horizon_s
from ajtwin.live.link import LinkRefused, OpcUaLink, _refusal, buffer_samples
from ajtwin.live.opcua import NAMESPACE_URI, SAMPLE_WIDTH, SETPOINTS, node_path
from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.simulation.job_print import load_camera_defaults

log = logging.getLogger("ajtwin.control")

WRITE_REFUSED = (
    "the server refused the set-point write ({code}): set-points may be written only by an "
    "authenticated user; give --username/--password (and --security on an encrypted server)"
)


@dataclass
class _Chunk:
    """New samples in the form :meth:`MPCTwin.observe` takes (a job print's columns too)."""

    time_s: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    shutter_open: np.ndarray | None = None
    platen_speed_mm_s: np.ndarray | None = None
    printed_at_s: np.ndarray | None = None


@dataclass
class ControlDecision:
    """One control period: what was decided and what was written."""

    time_s: float
    status: str  # act | hold | warm-up
    reason: str
    command: list  # [mA, sccm, sccm] in force after the period's write
    written: dict = field(default_factory=dict)  # {column: value} actually written
    solve_ms: float = float("nan")
    predicted_linewidth_um: float = float("nan")


class ControlLink:
    """Control one machine on an OPC UA server (see module docstring).

    Parameters
    ----------
    url : str
        ``opc.tcp://host:port``.
    machine : str
    target_um : float
        Target linewidth [µm].
    limits : dict, optional
        Machine limits {input column: [low, high]} (the registry's); intersected with
        the set-point nodes' ``EURange``.
    settings : ControlSettings, optional
    max_overspray_um : float, optional
    username, password, security, certificate, private_key, server_certificate
        As for :class:`~ajtwin.live.link.OpcUaLink`.
    on_decision : callable, optional
        Called with each :class:`ControlDecision` (the CLI prints them).
    job : ajtwin.job.Job, optional
        The program the machine prints (read with its speeds; run again over the same part
        when it ends): its shutter, speeds and camera geometry fill each sample's job columns
        (:class:`ajtwin.engine.job_samples.JobColumns`), the twin files the camera's frames
        at their print times and the MPC reads the seconds ahead.
    camera_mode : {"trailing", "at_nozzle"}
        The machine's camera on a job print.
    camera_offset_mm : (float, float), optional
        A trailing camera's view centre relative to the nozzle [mm] (default
        ``data/virtual_camera.toml``).
    engine : ajtwin.engine.fleet.LiveEngine, optional
        The machine's twin is the engine's (its print stored in the engine's registry with
        the job, every step published to its subscribers: the dashboard and the part map);
        default the controller's own.
    """

    def __init__(
        self,
        url: str,
        machine: str,
        target_um: float,
        *,
        limits: dict | None = None,
        settings=None,
        max_overspray_um: float | None = None,
        username: str | None = None,
        password: str | None = None,
        security: str | None = None,
        certificate=None,
        private_key=None,
        server_certificate=None,
        timeout_s: float = 4.0,
        max_backoff_s: float = 10.0,
        publish_ms: int = 100,
        on_decision=None,
        vial_fill_ml: float | None = None,
        job=None,
        camera_mode: str = "trailing",
        camera_offset_mm=None,
        engine=None,
    ):

        # the vial's fill as weighed at the refill: the start of the controller's ink
        # balance and of the vial observer (None: the twin's default, 1 mL)
        if vial_fill_ml is not None and not (np.isfinite(vial_fill_ml) and vial_fill_ml > 0):
            raise ValueError(f"vial fill = {vial_fill_ml!r} mL must be a positive number")
        self.vial_fill_ml = vial_fill_ml

        self.url, self.machine = url, machine
        self.target_um = check_target(target_um)
        self.settings = settings or ControlSettings.load()
        self.limits = {k: list(v) for k, v in (limits or DEFAULT_LIMITS).items()}
        self.max_overspray_um = max_overspray_um
        self.timeout_s = float(timeout_s)
        self.max_backoff_s = float(max_backoff_s)
        self.publish_ms = int(publish_ms)
        self.on_decision = on_decision
        # the client side of `ajtwin live` (login, security, certificates), no engine
        self._login = OpcUaLink(
            url,
            [machine],
            engine=None,
            username=username,
            password=password,
            security=security,
            certificate=certificate,
            private_key=private_key,
            server_certificate=server_certificate,
            timeout_s=timeout_s,
        )
        self.decisions: list[ControlDecision] = []
        self.last_time = -np.inf
        self.finished = False
        self.controller = None  # built by prepare() (compiles the twin and the MPC)
        self._next_decision_s = None
        self._last_write_s = None
        self._reach_checked = False
        if camera_mode not in ("trailing", "at_nozzle"):
            raise ValueError(
                f"camera {camera_mode!r}: live control follows a trailing camera or one at the "
                "nozzle (an inspection pass comes after the print)"
            )
        self.job, self.engine = job, engine
        self.camera = {
            "mode": camera_mode,
            "offset_mm": [0.0, 0.0]
            if camera_mode == "at_nozzle"
            else [float(v) for v in (camera_offset_mm or load_camera_defaults()["offset_mm"])],
        }
        self.columns = None  # JobColumns, made by prepare()
        self.print_id = None  # the engine's stored print, once finished

    # ------------------------------------------------------------------ setup
    def prepare(self):
        """Build the twin and the MPC (and compile them); done on the first connection
        unless called before (a test calls it before the server's clock starts)."""

        if self.controller is not None:
            return
        self.bounds = effective_bounds(self.limits)
        u_ref = np.array([np.mean(b) for b in self.bounds])
        fill = {} if self.vial_fill_ml is None else {"vial_fill_ml": float(self.vial_fill_ml)}
        twin, extra = Twin.default(**fill), {}
        if self.job is not None:
            extra = self._job_setup()
        if self.engine is not None:
            stream = self.engine.open(
                self.machine, source="control", print_context=extra.get("print_context")
            )
            twin = stream.twin
            extra.update(stream=stream, feed=functools.partial(self.engine.feed, self.machine))
        self.controller = MPCTwin(
            twin=twin,
            settings=self.settings,
            bounds=self.bounds,
            u0=u_ref,
            target=self.target_um,
            limits=self.limits,
            max_overspray_um=self.max_overspray_um,
            **extra,
        )

    def _job_setup(self) -> dict:
        """The looped job, the twin's print context and the sample columns of a job print."""
        looped = live_loop(self.job)
        # the horizon from two runs of the program (its delays repeat run after run)
        horizon = camera_horizon_s(self.camera, live_loop(self.job, 2 * self.job.duration_s))
        process = self.job.summary()["process_speed_mm_s"]
        context = PrintContext(horizon, self.camera["mode"], looped, process)
        self.columns = JobColumns(looped, self.camera["mode"], self.camera["offset_mm"])
        log.info("%s: job print, camera %s, horizon %g s", self.machine, self.camera, horizon)
        return {"job": looped, "print_context": context}

    def check_reachable(self, mean, cov) -> tuple[float, float]:
        """Once the twin has a state: is the target reachable within the limits from it?
        :class:`TargetError` with the reachable range when not (nothing is written)."""

        reach = reachable_linewidth(self.controller.twin, mean, cov, self.bounds)
        check_target(self.target_um, reach)
        self._reach_checked = True
        log.info("%s: reachable L_w %.1f–%.1f µm", self.machine, *reach)
        return reach

    def _apply_eu_ranges(self, ranges: dict) -> None:
        """Intersect the limits with the server's EURange of each set-point."""

        changed = False
        for column, (low, high) in ranges.items():
            lo, hi = self.limits[column]
            new = [max(lo, low), min(hi, high)]
            if not new[0] < new[1]:
                raise LinkRefused(
                    f"{self.url}: {self.machine} {column}: the server's range [{low}, {high}] "
                    f"and the machine limits [{lo}, {hi}] do not overlap"
                )
            if new != [lo, hi]:
                changed = True
                self.limits[column] = new
        if changed:
            self.bounds = effective_bounds(self.limits)
            mpc = type(self.controller.mpc)(
                self.controller.twin, self.settings, self.limits, self.max_overspray_um
            )
            mpc.warm_up()
            self.controller.mpc = mpc
            log.info("%s: limits narrowed to the server's EURange: %s", self.machine, self.limits)

    # ------------------------------------------------------------------ running
    async def run(self, stop: asyncio.Event | None = None) -> list[ControlDecision]:
        """Control until the print is finished (or ``stop`` is set); the decisions."""
        try:
            await self._run(stop)
        finally:
            if self.finished and self.engine is not None and self.controller is not None:
                # the print with its job, stored as an ordinary registry print
                self.print_id = self.engine.close(self.machine)
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
            if self.controller is None:  # compiled once we know we may write
                log.warning("%s: compiling the twin and the MPC …", self.machine)
                await asyncio.get_running_loop().run_in_executor(None, self.prepare)
            self._apply_eu_ranges(ranges)
            queue: asyncio.Queue = asyncio.Queue()

            class Handler:
                def datachange_notification(self, n, value, data):
                    queue.put_nowait((n.nodeid, value))

                def status_change_notification(self, status):
                    queue.put_nowait(("status", status))

            sub = await client.create_subscription(self.publish_ms, Handler())
            await sub.subscribe_data_change([buffer, state])
            log.info("%s: controlling %s to L_w = %g µm", self.url, self.machine, self.target_um)
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
                if fed and self.last_time >= self._next_decision_s:
                    await self._decide(setpoints)
                if time.monotonic() - last_check > 2.0:
                    await client.check_connection()
                    last_check = time.monotonic()

    def _feed(self, value) -> int:
        """New rows of the SampleBuffer → the twin; how many samples were fed."""
        try:  # the buffer's NaN padding (docs/reference/opcua.md) is not a problem worth a log line
            rows = np.asarray(value, dtype=float).reshape(-1, SAMPLE_WIDTH)
            value = rows[~np.all(np.isnan(rows), axis=1)]
        except (TypeError, ValueError, OverflowError):
            pass  # buffer_samples refuses it with a log line
        samples, self.last_time, problems = buffer_samples(self.machine, value, self.last_time)
        for p in problems:
            log.warning(p)
        if not samples:
            return 0
        if self._next_decision_s is None:
            self._next_decision_s = samples[0].time_s + self.settings.period_s
        chunk = _Chunk(
            np.array([x.time_s for x in samples]),
            np.array([x.inputs for x in samples]),
            np.array([x.outputs for x in samples]),
        )
        if self.columns is not None:
            columns = self.columns.fill(chunk.time_s, chunk.outputs)
            chunk.outputs = columns.pop("outputs")
            chunk = _Chunk(chunk.time_s, chunk.inputs, chunk.outputs, **columns)
        self.controller.observe(chunk)
        return len(samples)

    async def _read_setpoints(self, setpoints) -> np.ndarray:
        return np.array([float(await n.read_value()) for n in setpoints.values()])

    async def _decide(self, setpoints) -> None:

        s = self.settings
        t = float(self.last_time + 1)
        # the machine's own clock: a controller that lags behind its samples must not
        # bunch two periods' moves into less than a period of machine time
        machine_now = float(await self._clock.read_value())
        if self._last_write_s is not None and machine_now - self._last_write_s < s.period_s:
            self._next_decision_s = self.last_time + 1
            return
        self._next_decision_s = self.last_time + s.period_s
        u = await self._read_setpoints(setpoints)
        core = self.controller.stream.core
        if not self._reach_checked and core.n_committed:
            self.check_reachable(core.last_mean, core.last_cov)
        if t < s.warmup_s:
            decision = Decision(u.copy(), "warm-up", f"first {s.warmup_s} s of print")
        else:
            decision = await asyncio.get_running_loop().run_in_executor(
                None, self.controller.decide, t, u
            )
        max_step = np.asarray(s.rate_limits) * s.period_s  # ≥ one period since the last write
        command = clip_command(decision.command, u, self.bounds, max_step)
        changes, reason = {}, decision.reason
        for column, v, old in zip(setpoints, command, u):
            low, high = self.limits[column]
            if abs(float(v) - float(old)) <= 1e-9:
                continue
            if not low <= v <= high:  # on the way back from an operator's out-of-range value
                reason += f"; {column} {v:g} not written (outside [{low:g}, {high:g}])"
                continue
            changes[column] = float(v)
        if decision.status == "act" and changes:
            await self._write(setpoints, changes)
            self._last_write_s = float(await self._clock.read_value())
        else:
            changes = {}
        # what is in force now: the values read, with what was written
        command = [changes.get(column, float(old)) for column, old in zip(setpoints, u)]
        record = ControlDecision(
            t,
            decision.status,
            reason.lstrip("; "),
            [float(v) for v in command],
            changes,
            decision.solve_s * 1e3,
            decision.predicted_linewidth_um,
        )
        self.decisions.append(record)
        if decision.status in ("hold", "stop"):  # stop: latched, the ink ran low
            log.warning(
                "%s t = %.0f s: %s — %s", self.machine, t, decision.status.upper(), decision.reason
            )
        if self.on_decision:
            self.on_decision(record)

    async def _write(self, setpoints, values: dict, probe: bool = False) -> None:

        for column, value in values.items():
            if not probe:  # the probe writes back the machine's own values
                low, high = self.limits[column]
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


__all__ = ["ControlDecision", "ControlLink", "LinkRefused"]
