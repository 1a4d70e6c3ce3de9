"""What the live engine publishes: one typed message per machine and step.

Between the live link (``ajtwin.live``), the engine and the pages (``ajtwin.web``) travel
three kinds of message, each a frozen dataclass; :meth:`to_dict` gives the JSON-ready
form the dashboard's socket and ``ajtwin live --messages`` write
(docs/reference/live-messages.md). Names are the model's vocabulary
(:mod:`ajtwin.model.names`).

* :class:`StepMessage`: a step of one machine's twin, committed or provisional.
* :class:`LinkMessage`: the state of the link that feeds a machine.
* :class:`FinishedMessage`: the end of a machine's print, with its final events.

Examples
--------
>>> msg = LinkMessage("aj300-1", LinkState("connected", "opc.tcp://127.0.0.1:4840"))
>>> msg.to_dict()["link"]["state"]
'connected'
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ajtwin.apps.detection.settings import CUSUM_CHANNELS
from ajtwin.model.names import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES


def _named(names, values) -> dict[str, float]:
    return dict(zip(names, np.asarray(values, dtype=float).tolist()))


@dataclass(frozen=True)
class StepMessage:
    """One step of a machine's twin (display units).

    Attributes
    ----------
    machine : str
    step : int
        The step's number in the print (0 = its first second).
    time_s : float
        Its time on the record's clock [s].
    provisional : bool
        Not final: filtered with the previous θ while EM runs, or a job print's newest row
        (its step is committed H s later); not stored, not given to the detectors.
    states, stds : dict
        {state name: value} and σ as the twin reports it (the calibration's share and the
        never-seen floor included).
    covariance : array (5, 5)
        The reported covariance (kept out of :meth:`to_dict`).
    predicted_outputs, measured_outputs : dict
        {output name: value} (NaN = not measured).
    inputs : dict
        {input name: value} [mA, sccm, sccm].
    nis : float
        Normalised innovation squared.
    n_measured : int
    reinitialised : bool
        The divergence guard fired.
    theta : dict
        θ in force [1/s].
    em_running : bool
    status, cause : str
        ``warming up`` / ``ok`` / ``ok (provisional)`` / ``alarm``, and the latest cause.
    events : tuple of dict
        Events raised or finalised at this step: the detector's event record with
        ``state`` "raised" or "final".
    nis_p, window_nis_p : float or None
        NIS's χ² tail probability and the window's (committed steps).
    cusum : dict or None
        {channel: max(g⁺, g⁻)} (committed steps).
    alarms : tuple of str
        Detector labels that fired at this step.
    settling : dict or None
        "Ready to print" as of this step (:meth:`ajtwin.apps.detection.settling.
        SettlingDetector.status`): ``ready``, ``ready_at_s`` [s], ``evidence`` (per watched
        signal: trend per minute, change to come, tolerance) and ``text``; a new verdict
        after each atomizer restart.
    """

    machine: str
    step: int
    time_s: float
    provisional: bool
    states: dict
    stds: dict
    covariance: np.ndarray = field(repr=False)
    predicted_outputs: dict
    measured_outputs: dict
    inputs: dict
    nis: float
    n_measured: int
    reinitialised: bool
    theta: dict
    em_running: bool
    status: str
    cause: str
    events: tuple = ()
    nis_p: float | None = None
    window_nis_p: float | None = None
    cusum: dict | None = None
    alarms: tuple = ()
    settling: dict | None = None

    @property
    def input_values(self) -> np.ndarray:
        """u (3,) [mA, sccm, sccm]."""
        return np.array([self.inputs[n] for n in INPUT_NAMES], dtype=float)

    @property
    def output_values(self) -> np.ndarray:
        """The measured y (5,) (NaN = not measured)."""
        return np.array([self.measured_outputs[n] for n in OUTPUT_NAMES], dtype=float)

    @property
    def mean(self) -> np.ndarray:
        """x̂ (5,)."""
        return np.array([self.states[n] for n in STATE_NAMES], dtype=float)

    def raised(self) -> list[dict]:
        """The events raised at this step."""
        return [e for e in self.events if e.get("state") == "raised"]

    @classmethod
    def from_dict(cls, data: dict) -> StepMessage:
        """The message of its JSON form (:meth:`to_dict`; what the live log stores and a
        dashboard in another process reads back); the covariance from the σ alone."""
        stds = dict(data["stds"])
        return cls(
            machine=str(data["machine"]),
            step=int(data["step"]),
            time_s=float(data["time_s"]),
            provisional=bool(data.get("provisional", False)),
            states=dict(data["states"]),
            stds=stds,
            covariance=np.diag([float(stds[n]) ** 2 for n in STATE_NAMES]),
            predicted_outputs=dict(data["predicted_outputs"]),
            measured_outputs=dict(data["measured_outputs"]),
            inputs=dict(data["inputs"]),
            nis=float(data["nis"]),
            n_measured=int(data.get("n_measured", 0)),
            reinitialised=bool(data.get("reinitialised", False)),
            theta=dict(data["theta"]),
            em_running=bool(data.get("em_running", False)),
            status=str(data.get("status", "")),
            cause=str(data.get("cause", "")),
            events=tuple(data.get("events", ())),
            nis_p=data.get("nis_p"),
            window_nis_p=data.get("window_nis_p"),
            cusum=data.get("cusum"),
            alarms=tuple(data.get("alarms", ())),
            settling=data.get("settling"),
        )

    def to_dict(self) -> dict:
        """The JSON-ready message (docs/reference/live-messages.md)."""
        out = {
            "machine": self.machine,
            "step": self.step,
            "time_s": self.time_s,
            "provisional": self.provisional,
            "states": dict(self.states),
            "stds": dict(self.stds),
            "predicted_outputs": dict(self.predicted_outputs),
            "measured_outputs": dict(self.measured_outputs),
            "inputs": dict(self.inputs),
            "nis": self.nis,
            "n_measured": self.n_measured,
            "reinitialised": self.reinitialised,
            "theta": dict(self.theta),
            "em_running": self.em_running,
            "events": [dict(e) for e in self.events],
            "status": self.status,
            "cause": self.cause,
        }
        if self.settling is not None:
            out["settling"] = dict(self.settling)
        if self.cusum is not None:
            out.update(
                nis_p=self.nis_p,
                window_nis_p=self.window_nis_p,
                cusum=dict(self.cusum),
                alarms=list(self.alarms),
            )
        return out


@dataclass(frozen=True)
class LinkState:
    """The state of a machine link.

    ``state``: ``connecting``, ``connected`` (``gap_s``: how long the server was gone, None
    on the first connection; ``missed_s``: the print's first seconds the twin never saw, it
    joined late), ``reconnecting`` (gone since ``since``, Unix time; ``attempt`` failed
    attempts in this outage; ``retry_in_s`` the next back-off; ``reason`` the fault in
    words), ``refused`` (the link stops; ``reason``) or ``ended``.
    """

    state: str
    url: str = ""
    since: float | None = None
    attempt: int = 0
    retry_in_s: float | None = None
    reason: str = ""
    gap_s: float | None = None
    missed_s: float | None = None

    def to_dict(self) -> dict:
        """The JSON-ready link state."""
        return asdict(self)


@dataclass(frozen=True)
class LinkMessage:
    """The state of the link that feeds ``machine``."""

    machine: str
    link: LinkState

    def to_dict(self) -> dict:
        """The JSON-ready message."""
        return {"machine": self.machine, "link": self.link.to_dict()}


@dataclass(frozen=True)
class FinishedMessage:
    """The end of ``machine``'s print, with the events finalised at the end."""

    machine: str
    events: tuple = ()

    def to_dict(self) -> dict:
        """The JSON-ready message."""
        return {"machine": self.machine, "finished": True, "events": [dict(e) for e in self.events]}


#: what the engine publishes
Message = StepMessage | LinkMessage | FinishedMessage


def step_message(machine: str, block, i: int, detector_step, status: tuple, em_running: bool,
                 settling: dict | None = None):  # fmt: skip
    """Step ``i`` of a block of the twin's core (:class:`~ajtwin.estimation.online.
    StepBlock`), committed with the detectors' ``detector_step`` (None: provisional);
    ``settling`` the "ready to print" verdict as of the step."""
    f = block.filtered
    mean = np.asarray(f.means[i])
    message = dict(
        machine=machine,
        step=int(block.first + i),
        time_s=float(block.time_s[i]),
        provisional=detector_step is None,
        states=_named(STATE_NAMES, mean),
        stds=_named(STATE_NAMES, block.stds[i]),
        covariance=block.total_covariances()[i],
        predicted_outputs=_named(OUTPUT_NAMES, f.predicted_outputs[i]),
        measured_outputs=_named(OUTPUT_NAMES, block.measurements[i]),
        inputs=_named(INPUT_NAMES, block.inputs[i]),
        nis=float(f.nis[i]),
        n_measured=int(f.n_measured[i]),
        reinitialised=bool(f.reinitialised[i]),
        theta=_named(STATE_NAMES, block.theta),
        em_running=bool(em_running),
        status=status[0],
        cause=status[1],
        settling=settling,
    )
    if detector_step is not None:
        g = np.maximum(detector_step.cusum_pos, detector_step.cusum_neg)
        message.update(
            nis_p=float(detector_step.nis_p),
            window_nis_p=float(detector_step.window_nis_p),
            cusum=_named(CUSUM_CHANNELS, g),
            alarms=tuple(detector_step.alarms),
            events=tuple(
                [{"state": "raised", **ev.to_dict()} for ev in detector_step.raised]
                + [{"state": "final", **ev.to_dict()} for ev in detector_step.finalised]
            ),
        )
    return StepMessage(**message)


def provisional_message(machine: str, block, status: tuple, em_running: bool,
                        settling: dict | None = None) -> StepMessage:  # fmt: skip
    """The last step of a provisional block (:class:`~ajtwin.estimation.online.Provisional`
    carries it)."""
    return step_message(machine, block, len(block) - 1, None, status, em_running, settling)


def finished_message(machine: str, events) -> FinishedMessage:
    """The end of the print, with the detectors' final events."""
    return FinishedMessage(machine, tuple({"state": "final", **e.to_dict()} for e in events))
