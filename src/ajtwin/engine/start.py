"""The start of a print: where a machine's next print starts, and with which model.

On top of the chain's start (:func:`ajtwin.engine.chain.chain_start`: the newest good
print's end state and θ, the fields widened between prints) come the machine's newest
calibration (model reference §11) — and, when it was commissioned since its last print,
the state commissioning left it in — and the maintenance done since (a cleaned nozzle, a
refilled vial, a reset θ: :func:`apply_maintenance`). :func:`machine_start` puts these
together for an ingest and for the live twin alike; :func:`machine_twin` gives the twin
at a machine's current state for forecasts and advice.
"""

from __future__ import annotations

import numpy as np

from ajtwin.apps.detection.causes import open_faults
from ajtwin.engine.chain import carry_over, chain_start
from ajtwin.engine.commissioning import aerosol_level, calibration_twin_kwargs
from ajtwin.estimation.commission import load_commissioning_settings
from ajtwin.estimation.line_speed_fit import SpeedExponents
from ajtwin.estimation.twin import Twin
from ajtwin.store.calibration import active_calibration, pending_maintenance
from ajtwin.store.registry import RegistryError


def _maintenance_priors() -> tuple[float, float]:
    """Prior σ of a cleaned nozzle deposit [µm] and of a weighed refill [mL], as commissioning
    uses them."""
    prior = load_commissioning_settings()["state_prior"]
    return prior["nozzle_deposition_um"]["std"], prior["vial_volume_std_mL"]["value"]


def apply_maintenance(mean, cov, theta, events: list[dict]):
    """Start state (mean (5,), cov (5, 5)) and θ (5,) after maintenance events.

    Nozzle cleaned: ΔR_N → 0 with the cleaned-nozzle prior σ, uncorrelated with the rest
    (and θ_RN → 0: a clog learned into θ must not carry on). Vial refilled: V_l → fill
    with the weighing σ. Reset θ: θ → 0.
    """
    mean = np.array(mean, dtype=float)
    cov = np.array(cov, dtype=float)
    theta = np.array(theta, dtype=float)
    nozzle_std, vial_std = _maintenance_priors()

    def reset(index, value, std):
        mean[index] = value
        cov[index, :] = 0.0
        cov[:, index] = 0.0
        cov[index, index] = std**2

    for event in events:
        if event.get("nozzle_cleaned"):
            reset(3, 0.0, nozzle_std)
            theta[3] = 0.0
        if event.get("vial_refilled_ml") is not None:
            reset(1, float(event["vial_refilled_ml"]), vial_std)
        if event.get("reset_theta"):
            theta[:] = 0.0
    return mean, cov, theta


def commissioned_since_last_print(active: dict | None, chain) -> bool:
    """Whether the machine's newest calibration ``active`` was fitted after its newest print
    (then its next print starts where commissioning left the machine)."""
    latest = 0 if chain.latest_seq is None else chain.latest_seq
    return active is not None and active["after_print_seq"] >= latest


def machine_start(registry, machine: str, chain, twin_overrides: dict | None = None) -> dict:
    """How the machine's next print starts, on top of the chain's start (model reference §11).

    The newest calibration (if any) and its noise factors and covariance; if it was fitted
    after the newest print, the start is where commissioning left the machine; maintenance
    events done since are applied (:func:`apply_maintenance`). Returns a dict with
    ``start`` ((mean, cov) or None), ``theta`` (5,), ``twin_kwargs`` (for
    :meth:`Twin.default`), ``started_from``, ``calibration_id``, ``maintenance``.
    """
    active = active_calibration(registry, machine)
    commissioned = commissioned_since_last_print(active, chain)
    events = pending_maintenance(registry, machine, active["created_unix"] if commissioned else 0.0)
    begin = start_of_print(chain, active, commissioned, events, twin_overrides)
    begin["speed_exponents"] = carried_speed_exponents(registry, machine)
    return begin


def start_of_print(chain, active, commissioned: bool, events: list, twin_overrides=None) -> dict:
    """:func:`machine_start` from its parts: the chain's start (:class:`~ajtwin.engine.chain.
    ChainStart`), the calibration ``active`` (None: the nominal model), whether the print
    starts where that commissioning left the machine, and the maintenance ``events`` done
    before it. A stored print re-run in its place (:mod:`ajtwin.engine.reprocess`) starts
    the same way."""
    start = chain.start
    theta = np.zeros(5) if chain.theta is None else np.array(chain.theta, dtype=float)
    started_from = chain.description
    overrides = dict(twin_overrides or {})
    if commissioned:
        # start where commissioning left the machine, θ_φA holding its pinned atomizer level
        start = carry_over(active["end_mean"], active["end_cov"])
        theta[4] = aerosol_level(active).get("theta_per_s", 0.0)
        started_from = f"commissioning {active['id']}"
    if events:
        if start is None:
            refills = [e["vial_refilled_ml"] for e in events if e["vial_refilled_ml"] is not None]
            if refills:
                overrides.setdefault("vial_fill_ml", refills[-1])
        else:
            mean, cov, theta = apply_maintenance(start[0], start[1], theta, events)
            start = (mean, cov)
        started_from += " + maintenance"
    twin_kwargs = dict(overrides)
    if active is not None:
        twin_kwargs.update(calibration_twin_kwargs(active))
    return {
        "start": start,
        "theta": theta,
        "twin_kwargs": twin_kwargs,
        "started_from": started_from,
        "calibration_id": None if active is None else int(active["id"]),
        "maintenance": events,
    }


def carried_long_run_history(registry, machine: str, chain=None) -> dict | None:
    """The detectors' long-run noise statistics the machine's next print starts with.

    From its newest commissioning when that came after its last print (the print starts
    where commissioning left the machine, :func:`machine_start`),
    else from the newest print in the chain that stored them; None for a new machine (the
    detectors then start at scale 1 and learn it from the print).
    Without it a CUSUM meets a wandering gauge in the first minutes of every print with
    no scale for it (docs/explanation/detectors.md).
    """
    chain = chain if chain is not None else chain_start(registry, machine)
    active = active_calibration(registry, machine)
    if commissioned_since_last_print(active, chain) and active.get("long_run"):
        return active["long_run"]
    stored = registry.long_run_history(machine)
    return None if stored is None else stored[1]


def carried_speed_exponents(registry, machine: str, below_seq: int | None = None):
    """What the machine's prints have learnt of the speed law's exponents: the newest print
    in its chain (``below_seq``: before that print) that stored them
    (:class:`~ajtwin.estimation.line_speed_fit.SpeedExponents`), else None (the packaged
    law). A belief carried from print to print, the next print's prior."""
    for row in registry.chain_prints(machine, below_seq):
        stored = (row.get("summary") or {}).get("speed_exponents")
        if stored:
            return SpeedExponents.from_dict(stored)
    return None


def machine_open_faults(reg, name) -> tuple[int | None, list[dict]]:
    """The machine's newest print (its number, None without one) and the faults its alarms
    raised that no maintenance recorded since has closed
    (:func:`ajtwin.apps.detection.causes.open_faults`)."""
    newest = reg.last_print(name, in_chain=False)
    if newest is None:
        return None, []
    anomalies = reg.anomalies(name)
    events = anomalies[anomalies["seq"] == newest["seq"]].to_dict("records")
    return int(newest["seq"]), open_faults(events, pending_maintenance(reg, name), name)


def machine_twin(reg, name, nominal_theta=False, transition=None):
    """The twin at a machine's current state, as forecasts and advice start from it: the
    end of its last print with the maintenance recorded since (:func:`apply_maintenance`).

    Parameters
    ----------
    reg : Registry
    name : str
        A registered machine with at least one print in its chain.
    nominal_theta : bool
        θ = 0 instead of the machine's learned θ (e.g. after cleaning the nozzle).
    transition : str, optional
        A variant of ``data/transition.toml`` for the twin's droplet row (default: that
        file's default). A variant with a bounded θ_da prior (σ) clips the machine's
        learned θ_da to ±2σ.

    Returns
    -------
    tuple
        (twin with the machine's θ and calibration, mean (5,), cov (5, 5), the last
        print's final inputs (3,) [mA, sccm, sccm], machine row, last print row).

    Raises
    ------
    RegistryError
        An unknown machine, or one without a print to start from.
    """
    machine = reg.machine(name)
    last = reg.last_print(name)
    if last is None:
        raise RegistryError(
            f"machine {name!r} has no prints yet: ingest one first "
            f"(`ajtwin ingest --machine {name} print.parquet`)"
        )
    # the machine's calibration (model reference §11): forecasts and advice speak its outputs
    active = active_calibration(reg, name)
    calibrated = {} if active is None else calibration_twin_kwargs(active)
    chosen = {} if transition is None else {"transition": transition}
    twin = Twin.default(**chosen, **calibrated)
    learnt = carried_speed_exponents(reg, name)
    if learnt is not None:
        twin.learn_speed_law(learnt)
    if not nominal_theta:
        twin.theta = np.asarray(last["theta_after"], dtype=float)
        bound = 2.0 * twin.droplet_dynamics.theta_prior_std
        if twin.config.transition != "paper" and bound > 0:
            twin.theta[0] = float(np.clip(twin.theta[0], -bound, bound))
    inputs = reg.print_arrays(last["id"]).get("inputs")
    u_last = np.nanmedian(inputs[-60:], axis=0) if inputs is not None else np.array([375, 23, 50])
    # maintenance recorded since the last print (a cleaned nozzle, a refill) is the state now
    mean, cov, twin.theta = apply_maintenance(
        last["end_mean"], last["end_cov"], twin.theta, pending_maintenance(reg, name)
    )
    return twin, mean, cov, u_last, machine, last


def input_response_at_end(twin, reg, last):
    """The droplet size's input response at the end of the machine's last print.

    None when the twin's droplet row does not follow the inputs (equilibrium), or the
    print kept no inputs.
    """
    inputs = reg.print_arrays(last["id"]).get("inputs")
    if inputs is None or not np.isfinite(inputs).all():
        return None
    return twin.response_after(inputs)
