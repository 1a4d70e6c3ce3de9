"""The virtual printer as a live OPC UA server (``ajtwin printer serve``).

Each served machine is a virtual print played out in real or accelerated time (``speed``
simulated seconds per wall second) into the address space of :mod:`ajtwin.live.opcua`.
The print is made by the stepped virtual printer
(:class:`ajtwin.simulation.stepper.SteppedPrinter`, the one the closed-loop simulation
``ajtwin control simulate`` uses), advanced as far as it is published. A write to a
set-point within the machine's limits changes that input from the next unpublished
second on; nothing already printed changes, and a print without writes is
:func:`ajtwin.simulation.simulate`'s. A write outside the limits is refused (the old
value is written back).

Security: with users configured, anonymous sessions are refused; a wrong password is
``BadUserAccessDenied``. With ``certificate``/``private_key`` the server offers only the
``Basic256Sha256_SignAndEncrypt`` endpoint, and with ``trusted`` (a folder of client
certificates, DER or PEM) it accepts only those clients. Set-points can be written only
by an authenticated user; an anonymous session (allowed only when no users are
configured) may read everything and write only the ``Health`` folder (where a twin
publishes).

Examples
--------
>>> import asyncio                                                       # doctest: +SKIP
>>> server = PrinterServer("opc.tcp://127.0.0.1:4840", machines=[VirtualMachine(
...     "aj300-01", "nozzle_clog", seed=1, speed=30)])                   # doctest: +SKIP
>>> asyncio.run(server.serve_forever())                                 # doctest: +SKIP
"""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from asyncua import Server, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import ADMIN_TYPES, USER_TYPES, User, UserRole
from asyncua.ua.ua_binary import struct_from_binary as parse
from asyncua.ua.uaerrors import BadCertificateUntrusted
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from ajtwin import __version__
from ajtwin.io.records import INPUT_COLUMNS
from ajtwin.live.opcua import (
    ALARM_EVENT_TYPE,
    HEALTH_STATES,
    IDENTIFICATION,
    MACHINES_FOLDER,
    NAMESPACE_URI,
    PROCESS_VARIABLES,
    SAMPLE_COLUMNS,
    SAMPLE_WIDTH,
    SETPOINTS,
    node_path,
    unece_unit_id,
)
from ajtwin.model.limits import DEFAULT_LIMITS
from ajtwin.simulation.stepper import SteppedPrinter

log = logging.getLogger("ajtwin.printer")

#: rows of the SampleBuffer (a client that misses notifications for < this many
#: simulated seconds loses nothing)
BUFFER_ROWS = 300


@dataclass
class VirtualMachine:
    """One virtual printer played out in time.

    Parameters
    ----------
    name : str
    scenario : str
        A packaged scenario (``nozzle_clog``, ``exp1`` …).
    seed : int
    speed : float
        Simulated seconds per wall-clock second (1 = real time).
    duration_min : float, optional
    overrides : dict, optional
        Scenario overrides (e.g. an earlier fault onset).
    start_s : float
        Simulated time the serving starts at (a restarted server continues a print).
    limits : dict, optional
        Input limits {column: [low, high]} the set-points must respect
        (default: :data:`ajtwin.model.limits.DEFAULT_LIMITS`).
    job : str, Path or ajtwin.job.Job, optional
        A machine program the printer runs (looped to the print's length; the default
        camera trails the nozzle): served samples have no line while nothing is printed
        or seen (:class:`~ajtwin.simulation.stepper.SteppedPrinter`).
    print_id : str, optional
        The print's identity served as ``PrintId`` (default: a new one each time the
        machine is made; give the old one with ``start_s`` to continue a print).
    """

    name: str
    scenario: str = "nozzle_clog"
    seed: int = 0
    speed: float = 1.0
    duration_min: float | None = None
    overrides: dict | None = None
    start_s: float = 0.0
    limits: dict | None = None
    schedule: dict = field(default_factory=dict, repr=False)
    job: object = None
    print_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])

    #: largest block of seconds simulated in one call (powers of two up to this: few
    #: compilations of the stepper's scan whatever the publishing rhythm)
    MAX_BLOCK_S = 64

    def __post_init__(self):

        if self.limits is None:
            self.limits = copy.deepcopy(DEFAULT_LIMITS)
        self.printer = SteppedPrinter(
            self.scenario, self.seed, self.duration_min, self.overrides, job=self.job
        )
        # the served samples (rows of SAMPLE_COLUMNS), filled as the print advances
        self._samples = np.full((self.printer.n, SAMPLE_WIDTH), np.nan)
        self._lock = threading.Lock()  # set-point writes run in an executor thread
        self._t0 = None

    def start(self, now: float) -> None:
        """Start the simulated clock at wall time ``now`` [s] (at ``start_s`` simulated)."""
        self._t0 = now - self.start_s / self.speed

    def simulated_time(self, now: float) -> float:
        """The simulated print time [s] at wall time ``now`` [s]."""
        return (now - self._t0) * self.speed

    @property
    def n_samples(self) -> int:
        """Seconds of the whole print."""
        return self.printer.n

    @property
    def setpoints(self) -> np.ndarray:
        """The commands in force now [I_A mA, Q_c sccm, Q_s sccm]."""
        return self.printer.schedule[min(self.printer.k, self.printer.n - 1)].copy()

    @property
    def record(self):
        """The print so far (measured columns and truth) as a record."""
        with self._lock:
            return self.printer.record()

    @property
    def true_outputs(self) -> np.ndarray:
        """Noise-free outputs (k, 5) printed so far (what a test compares a controller to)."""
        return self.printer.true_outputs

    def warm_up(self) -> None:
        """Step a throwaway printer of the same print through every block size served
        (:attr:`MAX_BLOCK_S`): their programs compiled before the print starts, the first
        seconds served do not hold the server's loop (2-4 s, long enough for a connected
        client to time out)."""
        printer = SteppedPrinter(
            self.scenario, self.seed, self.duration_min, self.overrides, job=self.job
        )
        block = 1
        while block <= self.MAX_BLOCK_S and printer.k + block <= printer.n:
            printer.advance(block)
            block *= 2

    def advance_to(self, stop: int) -> None:
        """Print up to (not including) second ``stop``."""
        with self._lock:
            self._advance_to(stop)

    def _advance_to(self, stop: int) -> None:
        printer = self.printer
        stop = min(int(stop), printer.n)
        while printer.k < stop:
            block = min(self.MAX_BLOCK_S, 1 << int(np.log2(stop - printer.k)))
            chunk = printer.advance(block)
            rows = chunk.time_s.astype(int)
            self._samples[rows, 0] = chunk.time_s
            self._samples[rows, 1:4] = chunk.inputs
            self._samples[rows, 4:] = chunk.outputs

    def rows(self, stop: int, count: int) -> np.ndarray:
        """The last ``count`` samples before index ``stop``, (n, 9) with NaN padding."""
        self.advance_to(stop)
        lo = max(0, stop - count)
        block = np.full((count, SAMPLE_WIDTH), np.nan)
        if stop > lo:
            block[count - (stop - lo) :] = self._samples[lo:stop]
        return block

    def set_point(self, column: str, value: float, at_s: float) -> str | None:
        """Apply a set-point from simulated second ceil(at_s + 1); a refusal message or None.

        The print is advanced to that second and the stepper takes the command from
        there (the other two inputs keep their schedule).
        """
        low, high = self.limits[column]
        if not np.isfinite(value) or not (low <= value <= high):
            return f"{self.name}: {column} = {value!r} outside the machine limits [{low}, {high}]"
        second = int(np.ceil(at_s + 1.0))
        with self._lock:
            if second >= self.printer.n:
                return f"{self.name}: the print is over; {column} not changed"
            self._advance_to(second)
            second = self.printer.k  # a write that arrives late applies from now
            self.printer.set_input(INPUT_COLUMNS.index(column), float(value))
        self.schedule[column] = [s for s in self.schedule.get(column, []) if s[0] * 60 < second]
        self.schedule[column].append([second / 60.0, float(value)])
        return None


class _Ruleset:
    """Who may do what: anonymous reads and writes Health only; users everything."""

    def __init__(self):

        self._ua = ua
        self._role = UserRole
        self._user = {ua.NodeId(t) for t in USER_TYPES}
        self._admin = self._user | {ua.NodeId(t) for t in ADMIN_TYPES}
        self._write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)

    def check_validity(self, user, action_type_id, body):
        role = getattr(user, "role", self._role.Anonymous)
        if role == self._role.Admin:
            return action_type_id in self._admin
        if role == self._role.User:
            return action_type_id in self._user
        if action_type_id == self._write:
            try:
                params = parse(self._ua.WriteParameters, body.copy())
                ids = [str(w.NodeId.Identifier) for w in params.NodesToWrite]
            except Exception:
                return False
            return all("/Monitoring/Health/" in i for i in ids)
        return action_type_id in self._user


class _Users:
    """Username/password users (and trusted client certificates as users)."""

    def __init__(self, users: dict[str, str], allow_anonymous: bool, trust_certificates: bool):

        self.users = dict(users)
        self.allow_anonymous = allow_anonymous
        # the channel's client certificate is passed for every token; it identifies a user
        # only when the server checks it against a trusted folder
        self.trust_certificates = trust_certificates
        self._user, self._role = User, UserRole

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username is not None:
            if username in self.users and self.users[username] == password:
                return self._user(role=self._role.User, name=username)
            log.warning("refused login of user %r: wrong user name or password", username)
            return None
        if certificate and self.trust_certificates:
            return self._user(role=self._role.User, name="trusted certificate")
        if self.allow_anonymous:
            return self._user(role=self._role.Anonymous)
        return None


async def ensure_certificate(certificate: Path, private_key: Path, host: str, app_uri: str):
    """Create a self-signed certificate (DER) and key (PEM) unless both exist."""

    Path(certificate).parent.mkdir(parents=True, exist_ok=True)
    await setup_self_signed_certificate(
        Path(private_key),
        Path(certificate),
        app_uri,
        host,
        [ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH],
        {"commonName": app_uri},
    )


class PrinterServer:
    """Virtual printers served over OPC UA (see module docstring).

    Parameters
    ----------
    endpoint : str
        ``opc.tcp://host:port``.
    machines : list of VirtualMachine
    users : dict, optional
        {user name: password}; when given, anonymous access is off.
    certificate, private_key : path, optional
        Server certificate (DER) and key (PEM): offer only Basic256Sha256_SignAndEncrypt.
    trusted : path, optional
        Folder of trusted client certificates (others are refused).
    tick_s : float
        Wall-clock period of the publishing loop.
    buffer_rows : int
        Rows of each machine's ``SampleBuffer``.
    wait_for_client : bool
        Hold every print at its start until a client has subscribed (a twin started after
        the server misses nothing of the print).
    """

    def __init__(
        self,
        endpoint: str,
        machines: list[VirtualMachine],
        *,
        users: dict | None = None,
        certificate=None,
        private_key=None,
        trusted=None,
        tick_s: float = 0.1,
        buffer_rows: int = BUFFER_ROWS,
        wait_for_client: bool = False,
    ):
        self.buffer_rows = int(buffer_rows)
        self.wait_for_client = bool(wait_for_client)
        self.endpoint = endpoint
        self.machines = {m.name: m for m in machines}
        self.users = dict(users or {})
        self.certificate = certificate
        self.private_key = private_key
        self.trusted = trusted
        self.tick_s = float(tick_s)
        self.nodes: dict[str, dict] = {}
        self.server = None
        self._sent: dict[str, int] = {}

    async def _build(self):

        users = _Users(
            self.users, allow_anonymous=not self.users, trust_certificates=bool(self.trusted)
        )
        server = Server(user_manager=users)
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("ajtwin virtual Aerosol Jet printers")
        await server.set_application_uri("urn:ajtwin:virtual-printer")
        tokens = [ua.UserNameIdentityToken] if self.users else [ua.AnonymousIdentityToken]
        if self.certificate:
            await server.load_certificate(str(self.certificate))
            await server.load_private_key(str(self.private_key))
            policies = [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt]
            tokens.append(ua.X509IdentityToken)
        else:
            policies = [ua.SecurityPolicyType.NoSecurity]
        server.set_identity_tokens(tokens)
        server.set_security_policy(policies, permission_ruleset=_Ruleset())
        if self.trusted:
            server.set_certificate_validator(_trust_validator(Path(self.trusted)))
        idx = await server.register_namespace(NAMESPACE_URI)
        self.idx = idx
        event_type = await server.create_custom_event_type(
            idx,
            ALARM_EVENT_TYPE,
            ua.ObjectIds.BaseEventType,
            [
                ("Machine", ua.VariantType.String),
                ("Cause", ua.VariantType.String),
                ("OnsetTime", ua.VariantType.Double),
                ("DetectedTime", ua.VariantType.Double),
                ("Detectors", ua.VariantType.String),
                ("AlarmState", ua.VariantType.String),
            ],
        )
        self.event_generator = await server.get_event_generator(event_type)
        folder = await server.nodes.objects.add_folder(
            ua.NodeId(MACHINES_FOLDER, idx), f"{idx}:{MACHINES_FOLDER}"
        )
        for name, machine in self.machines.items():
            self.nodes[name] = await self._add_machine(folder, idx, name, machine)
        self.server = server

    async def _add_machine(self, folder, idx, name, machine) -> dict:

        def nid(*parts):
            return ua.NodeId(node_path(name, *parts), idx)

        obj = await folder.add_object(nid(), f"{idx}:{name}")
        nodes = {}
        ident = await obj.add_object(nid("Identification"), f"{idx}:Identification")
        values = {
            "Manufacturer": "ajtwin (virtual printer)",
            "Model": "virtual AJ 300",
            "SerialNumber": name,
            "ProductInstanceUri": f"urn:ajtwin:machine:{name}",
            "SoftwareRevision": _version(),
        }
        for key in IDENTIFICATION:
            await ident.add_property(nid("Identification", key), f"{idx}:{key}", values[key])
        monitoring = await obj.add_object(nid("Monitoring"), f"{idx}:Monitoring")
        process = await monitoring.add_object(nid("Monitoring", "Process"), f"{idx}:Process")
        for key, (column, unit, code) in PROCESS_VARIABLES.items():
            var = await process.add_variable(
                nid("Monitoring", "Process", key), f"{idx}:{key}", float("nan")
            )
            await _engineering_units(var, idx, nid("Monitoring", "Process", key, "EU"), unit, code)
            nodes[column] = var
        nodes["time"] = await process.add_variable(
            nid("Monitoring", "Process", "SampleTime"), f"{idx}:SampleTime", -1.0
        )
        nodes["state"] = await process.add_variable(
            nid("Monitoring", "Process", "PrintState"), f"{idx}:PrintState", "printing"
        )
        # which print the samples belong to: a client tells a restarted machine's new print
        # from the one it followed (docs/reference/opcua.md)
        nodes["print_id"] = await process.add_variable(
            nid("Monitoring", "Process", "PrintId"), f"{idx}:PrintId", machine.print_id
        )
        nodes["buffer"] = await process.add_variable(
            nid("Monitoring", "Process", "SampleBuffer"),
            f"{idx}:SampleBuffer",
            ua.Variant(machine.rows(0, self.buffer_rows).ravel().tolist(), ua.VariantType.Double),
        )
        setpoints = await monitoring.add_object(nid("Monitoring", "SetPoints"), f"{idx}:SetPoints")
        nodes["setpoints"] = {}
        first = machine.setpoints
        for i, (key, (column, unit, code)) in enumerate(SETPOINTS.items()):
            var = await setpoints.add_variable(
                nid("Monitoring", "SetPoints", key), f"{idx}:{key}", float(first[i])
            )
            await var.set_writable()
            await _engineering_units(
                var,
                idx,
                nid("Monitoring", "SetPoints", key, "EU"),
                unit,
                code,
                machine.limits[column],
            )
            nodes["setpoints"][column] = var
        health = await monitoring.add_object(nid("Monitoring", "Health"), f"{idx}:Health")
        defaults = {"Status": "no twin connected", "Cause": "", "Alarm": "", "TwinTime": -1.0}
        defaults["LinkStatus"] = ""  # the twin's link: connected since …, back after a gap
        defaults["NIS"] = float("nan")
        defaults["Theta"] = [0.0] * 5
        for key, (_state, unit, code) in HEALTH_STATES.items():
            for suffix in ("", "Std"):
                var = await health.add_variable(
                    nid("Monitoring", "Health", key + suffix), f"{idx}:{key}{suffix}", float("nan")
                )
                await var.set_writable()
                await _engineering_units(
                    var, idx, nid("Monitoring", "Health", key + suffix, "EU"), unit, code
                )
        for key, value in defaults.items():
            var = await health.add_variable(nid("Monitoring", "Health", key), f"{idx}:{key}", value)
            await var.set_writable()
            if key == "Alarm":
                nodes["alarm"] = var
        return nodes

    # ------------------------------------------------------------------ #
    async def _watch(self):
        """Server-side subscription: set-point writes and twin alarms."""
        server = self
        setpoint_nodes = {}
        for name, nodes in self.nodes.items():
            for column, var in nodes["setpoints"].items():
                setpoint_nodes[var.nodeid] = (name, column, var)
        alarm_nodes = {nodes["alarm"].nodeid: name for name, nodes in self.nodes.items()}

        pending: list = []

        async def flush():
            # the changes of one notification (e.g. a client's three set-points in one
            # write request) are applied together, from the same second
            batch, pending[:] = list(pending), []
            now = time.monotonic()
            for node, value in batch:
                await server._on_change(node, value, now)

        class Handler:
            def datachange_notification(self, node, value, data):
                if not pending:
                    asyncio.get_event_loop().call_soon(
                        lambda: asyncio.get_event_loop().create_task(flush())
                    )
                pending.append((node, value))

        sub = await self.server.create_subscription(50, Handler())
        await sub.subscribe_data_change([v for _, _, v in setpoint_nodes.values()])
        await sub.subscribe_data_change([self.nodes[n]["alarm"] for n in self.nodes])
        self._setpoint_nodes = setpoint_nodes
        self._alarm_nodes = alarm_nodes
        self._last_setpoint = {k: None for k in setpoint_nodes}
        return sub

    async def _on_change(self, node, value, now: float):
        if node.nodeid in self._alarm_nodes:
            if value:
                await self._fire_alarm(self._alarm_nodes[node.nodeid], value)
            return
        name, column, var = self._setpoint_nodes[node.nodeid]
        machine = self.machines[name]
        previous = self._last_setpoint[node.nodeid]
        self._last_setpoint[node.nodeid] = value
        if previous is None:
            return  # the initial notification
        now_s = machine.simulated_time(now)
        # in the loop, not an executor: stepping to the write's second is short, and the
        # publishing loop must not run past that second meanwhile (the write would land late)
        refusal = machine.set_point(column, float(value), now_s)
        if refusal:
            log.warning("set-point refused: %s", refusal)
            self._last_setpoint[node.nodeid] = previous
            await var.write_value(float(previous))
        else:
            log.info("%s: %s set to %g from t = %.0f s", name, column, float(value), now_s + 1)

    async def _fire_alarm(self, machine: str, text: str):
        try:
            event = json.loads(text)
        except ValueError:
            log.warning("%s: Health/Alarm is not JSON: %r", machine, text[:80])
            return
        gen = self.event_generator
        gen.event.Machine = machine
        gen.event.Cause = str(event.get("cause", ""))
        gen.event.OnsetTime = float(event.get("onset_s", float("nan")))
        gen.event.DetectedTime = float(event.get("detected_s", float("nan")))
        gen.event.Detectors = ", ".join(event.get("detectors", []))
        gen.event.AlarmState = str(event.get("state", ""))
        gen.event.Severity = 800
        gen.event.SourceName = machine
        await gen.trigger(
            message=f"{machine}: {event.get('description', event.get('cause', 'anomaly'))}"
        )

    async def _publish(self, now: float) -> bool:
        """Write every machine's new samples; False when all prints have finished."""

        running = False
        for name, machine in self.machines.items():
            nodes = self.nodes[name]
            n = machine.n_samples
            stop = min(n, int(np.floor(machine.simulated_time(now))) + 1)
            if stop < n:
                running = True
            if stop <= self._sent.get(name, 0):
                continue
            self._sent[name] = stop
            block = machine.rows(stop, self.buffer_rows)
            row = block[-1]
            for column, *_ in PROCESS_VARIABLES.values():
                await nodes[column].write_value(float(row[SAMPLE_COLUMNS.index(column)]))
            await nodes["buffer"].write_value(
                ua.Variant(block.ravel().tolist(), ua.VariantType.Double)
            )
            await nodes["time"].write_value(float(row[0]))
            if stop >= n:
                await nodes["state"].write_value("finished")
        return running

    def _warm_up(self) -> None:
        """Each distinct print's stepper compiled (:meth:`VirtualMachine.warm_up`)."""
        seen = set()
        for m in self.machines.values():
            key = (m.scenario, m.duration_min, id(m.job))
            if key not in seen:
                seen.add(key)
                m.warm_up()

    async def _client_subscribed(self, stop_event) -> bool:
        """Wait until a client's subscription exists (beyond the server's own); False when
        ``stop_event`` came first."""
        service = self.server.iserver.subscription_service
        own = len(service.subscriptions)  # the server's subscription to its set-points
        log.info("waiting for a client to subscribe; the prints start then")
        while len(service.subscriptions) <= own:
            if stop_event is not None and stop_event.is_set():
                return False
            await asyncio.sleep(0.05)
        log.info("a client subscribed: the prints start")
        return True

    async def serve(self, stop_event: asyncio.Event | None = None, on_ready=None):
        """Run until every print has finished (then keep serving) or ``stop_event`` is set;
        ``on_ready()`` once clients can connect (with ``wait_for_client``, before the prints
        start)."""
        await self._build()
        async with self.server:
            await self._watch()
            if self.wait_for_client and on_ready:
                on_ready()
                on_ready = None
            await asyncio.to_thread(self._warm_up)  # clients may connect meanwhile
            if self.wait_for_client and not await self._client_subscribed(stop_event):
                return
            now = time.monotonic()
            for m in self.machines.values():
                m.start(now)
            log.info(
                "serving %d virtual printer(s) at %s (x%g)",
                len(self.machines),
                self.endpoint,
                next(iter(self.machines.values())).speed,
            )
            if on_ready:
                on_ready()
            finished_logged = False
            while stop_event is None or not stop_event.is_set():
                running = await self._publish(time.monotonic())
                if not running and not finished_logged:
                    log.info("all prints finished; still serving")
                    finished_logged = True
                await asyncio.sleep(self.tick_s)


async def _engineering_units(var, idx, nodeid, unit: str, code: str, eu_range=None):

    info = ua.EUInformation(
        NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
        UnitId=unece_unit_id(code),
        DisplayName=ua.LocalizedText(unit),
        Description=ua.LocalizedText(unit),
    )
    await var.add_property(nodeid, "EngineeringUnits", info)
    if eu_range is not None:
        rng = ua.Range(Low=float(eu_range[0]), High=float(eu_range[1]))
        await var.add_property(ua.NodeId(str(nodeid.Identifier) + "Range", idx), "EURange", rng)


def _trust_validator(folder: Path):
    """A certificate validator that accepts only the client certificates in ``folder``."""

    trusted = set()
    for path in sorted(folder.glob("*")):
        data = path.read_bytes()
        try:
            cert = x509.load_der_x509_certificate(data)
        except ValueError:
            try:
                cert = x509.load_pem_x509_certificate(data)
            except ValueError:
                continue
        trusted.add(cert.public_bytes(Encoding.DER))

    async def validate(cert, app_description):
        if cert.public_bytes(Encoding.DER) not in trusted:
            log.warning(
                "refused client %s: certificate not in the trusted folder %s",
                getattr(app_description, "ApplicationUri", "?"),
                folder,
            )
            raise BadCertificateUntrusted

    return validate


def _version() -> str:

    return __version__
