"""The likely cause of an anomaly, from the pattern of output innovations and state
corrections (paper §4 "applications"): nozzle clog, carrier leak, atomizer trouble, ink
running out, or unexplained.
"""

from __future__ import annotations

import functools

import numpy as np

from ajtwin import units
from ajtwin.apps.detection.settings import DetectorSettings
from ajtwin.config import packaged_toml

#: The likely-cause labels (paper §4).
CAUSES = {
    "nozzle_clog": "nozzle clog (both pressures rising, ΔR_N growing)",
    "carrier_leak": (
        "carrier leak, MFC drift or carrier-pressure sensor drift (P_c falling or alone)"
    ),
    "atomizer": "atomizer trouble (Q_m and φ_A falling)",
    "ink_low": "ink running out (V_l low or falling towards it; vial observer)",
    "unexplained": "unexplained deviation",
    # set by AnomalyDetector when the nozzle deposit leaves the output model's range
    "nozzle_cleaning": (
        "nozzle needs cleaning (its deposit is beyond the range the output model was built "
        "for; the print's later alarms are part of this event)"
    ),
    # set by AnomalyDetector for an event the atomizer's run-in explains (RUN_IN_EXPLAINS)
    "run_in": (
        "atomizer running in (the mist still building up after switch-on, before ready to "
        "print): not a fault"
    ),
    # set by ajtwin.apps.detection.mismatch.relabel_events: the model does not fit the machine
    "model_machine_mismatch": "model–machine mismatch, not a fault (commission the machine)",
}

#: the causes a run-in explains when the event began in one and none of its alarms is on the
#: pressures or the vial (:meth:`~ajtwin.apps.detection.streaming.AnomalyDetector.
#: _run_in_explains`): a mist building up looks like the atomizer delivering less, or more,
#: than the twin expects, and the twin's corrections of d_a and φ_A move the pressures' means
#: enough for a carrier-leak pattern; a clog label (a growing deposit) is never the run-in's
RUN_IN_EXPLAINS = ("atomizer", "unexplained", "carrier_leak")


def label_cause(
    mean_innovation,
    n_samples,
    state_shift,
    vial_mL: float,
    settings: DetectorSettings,
    vial_running_low: bool | None = None,
) -> str:
    """The likely cause from the pattern of outputs and states.

    Parameters
    ----------
    mean_innovation : (5,) mean normalised innovation per output over the evidence window
    n_samples : (5,) number of measured samples behind each mean
    state_shift : (5,) filter corrections Σ(x̂_k − x̂_{k|k−1}) over the window, divided
        by the state's σ at detection (signed: which state the data pushed, and which way)
    vial_mL : latest V_l estimate [mL] (the twin's; used when there is no observer)
    vial_running_low : the vial observer's flag (:mod:`ajtwin.estimation.vial`) at the
        end of the evidence window, or None without one. The twin's own V_l is a
        consider state (it follows the fill and the modelled draw), so with the observer
        it decides 'ink running out'; a Q_m deficit it does not read as the vial is
        left to the other rules (atomizer …).

    Returns
    -------
    One key of :data:`CAUSES`.

    Examples
    --------
    >>> s = DetectorSettings()
    >>> label_cause([1, 1, 2, 2, 0], [60] * 5, [0, 0, 0, 5, 0], 1.0, s)
    'nozzle_clog'
    >>> label_cause([0, 0, -2, 0, -1], [60] * 5, [0, 0, 0, 0, -1], 1.0, s)
    'carrier_leak'
    >>> label_cause([-1, 0, 0, 0, -2], [60] * 5, [0, 0, 0, 0, -4], 1.0, s)
    'atomizer'
    >>> label_cause([-1, 0, 0, 0, -2], [60] * 5, [0, 0, 0, 0, -4], 1.0, s, True)
    'ink_low'
    """
    if vial_running_low is not None:
        # the vial observer sees the vial apart from the atomizer: it decides
        if vial_running_low:
            return "ink_low"
        vial_mL = np.nan
    m = np.asarray(mean_innovation, dtype=float)
    n = np.asarray(n_samples, dtype=float)
    z = np.nan_to_num(m * np.sqrt(np.maximum(n, 0)))
    shift = np.nan_to_num(np.asarray(state_shift, dtype=float))
    sig = np.abs(z) > settings.significance_z
    lw, lo, pc, ps, qm = range(5)
    if np.isfinite(vial_mL) and vial_mL < settings.vial_low_mL:
        return "ink_low"
    zs = settings.significance_z
    # a physical change in the nozzle moves both pressures the same way (shared
    # (Q_c + Q_s)·R_N term); rising together = deposit
    if z[pc] > zs and z[ps] > zs and (shift[3] > 0 or z[lw] > 0 or z[lo] > 0):
        return "nozzle_clog"
    # both pressures up, the filter reading them as a growing nozzle deposit (ΔR_N pushed
    # up by many σ), though P_s's rise is still within its noise in the evidence window: a
    # clog's start, not the carrier line (a leak LOWERS P_c; a gauge creeping up alone
    # pushes ΔR_N while P_s falls below the deposit's prediction). Held-out alt machines
    # 1037/1042: P_c +0.73/+0.77σ, P_s +0.23/+0.20σ, ΔR_N +49/+58σ were labelled carrier
    # leak by the rule below
    if shift[3] > zs and z[pc] > zs and z[ps] > 0:
        return "nozzle_clog"
    # less carrier reaching the head lowers P_c (and P_s through the nozzle); a P_c
    # change alone or against P_s is the carrier line or its sensor
    if z[pc] < -zs or (sig[pc] and (not sig[ps] or np.sign(z[pc]) != np.sign(z[ps]))):
        return "carrier_leak"
    if not (sig[pc] or sig[ps]) and (z[qm] < -zs or shift[4] < -zs):
        return "atomizer"
    if z[pc] > zs and z[ps] > zs:
        return "nozzle_clog"
    # the filter reads the pressures as a growing nozzle deposit (ΔR_N pushed up by many σ)
    # and together they rose, though one gauge's mean stayed within its noise (alt
    # generator, held-out machines 1006/1013: P_s +0.7σ, P_c +0.15σ, ΔR_N +37…46σ)
    if shift[3] > zs and min(z[pc], z[ps]) > -zs and z[pc] + z[ps] > zs:
        return "nozzle_clog"
    return "unexplained"


# --------------------------------------------------------------------------- #
# What a person is told: the cause in words and what to do (data/causes.toml)
# --------------------------------------------------------------------------- #


@functools.cache
def _advice() -> dict:
    """``data/causes.toml``: per cause its words, action and maintenance option; the
    detectors' labels in words."""
    return packaged_toml("data/causes.toml")


def cause_keys() -> tuple[str, ...]:
    """The causes ``data/causes.toml`` has words and an action for.

    >>> "nozzle_clog" in cause_keys()
    True
    """
    return tuple(_advice()["causes"])


def cause_words(cause: str) -> str:
    """What is happening, as an operator says it (``'nozzle clogging'``); an unknown cause
    key is returned as its words with underscores as spaces.

    >>> cause_words("nozzle_clog")
    'nozzle clogging'
    """
    entry = _advice()["causes"].get(str(cause))
    return entry["words"] if entry else str(cause).replace("_", " ")


def cause_action(cause: str, machine: str | None = None) -> str:
    """What to do about ``cause`` (``machine``: its name in the command to run; None:
    ``MACHINE``); ``''`` for an unknown cause.

    >>> cause_action("nozzle_clog", "lab1")
    'clean the nozzle, then `ajtwin machine maintain lab1 --nozzle-cleaned`'
    """
    entry = _advice()["causes"].get(str(cause))
    return entry["action"].format(machine=machine or "MACHINE") if entry else ""


def alarm_sentence(cause: str, since_s: float | None = None, machine: str | None = None) -> str:
    """One line on an alarm: the cause in words, since when (minutes past the print's start)
    and the action.

    >>> alarm_sentence("carrier_leak", 3540.0, "lab1")[:42]
    'carrier gas line leaking, or its flow cont'
    >>> alarm_sentence("nozzle_clog", 3540.0, "lab1").split(": ")[0]
    'nozzle clogging since 59.0 min'
    """
    since = "" if since_s is None else f" since {units.minutes_text(since_s)}"
    action = cause_action(cause, machine)
    return f"{cause_words(cause)}{since}" + (f": {action}" if action else "")


def detector_words(label: str) -> str:
    """A detector's label in words first, the label after it in brackets:
    ``'both gas pressures rising together (cusum+ P_c+P_s)'``.

    >>> detector_words("deposit push ΔR_N")
    'the filter reading a growing nozzle deposit (deposit push ΔR_N)'
    """
    words = _advice()["detectors"]
    fits = [prefix for prefix in words if str(label).startswith(prefix)]
    if not fits:
        return str(label)
    return f"{words[max(fits, key=len)]} ({label})"


def closing_maintenance(cause: str, maintenance) -> int | None:
    """Which of ``maintenance`` (events oldest first, as ``ajtwin machine maintain`` stores
    them) first closes a fault of ``cause``: its index, or None (none does, or the cause is
    no fault of the machine).

    >>> closing_maintenance("nozzle_clog", [{"vial_refilled_ml": 2.0}, {"nozzle_cleaned": True}])
    1
    >>> closing_maintenance("nozzle_clog", [{"vial_refilled_ml": 2.0}]) is None
    True
    """
    entry = _advice()["causes"].get(str(cause))
    if entry is None or not entry["fault"]:
        return None
    key = entry["fixed_by"]  # "": any maintenance recorded after the print
    return next((i for i, m in enumerate(maintenance) if not key or bool(m.get(key))), None)


def maintenance_words(event: dict) -> str:
    """A maintenance event as the commands say it.

    >>> maintenance_words({"nozzle_cleaned": True, "vial_refilled_ml": 1.5, "note": "seal"})
    'nozzle cleaned, vial refilled to 1.5 mL, note "seal"'
    """
    done = [
        "nozzle cleaned" if event.get("nozzle_cleaned") else "",
        f"vial refilled to {event['vial_refilled_ml']:g} mL"
        if event.get("vial_refilled_ml")
        else "",
        "θ reset" if event.get("reset_theta") else "",
        f'note "{event["note"]}"' if event.get("note") else "",
    ]
    return ", ".join(d for d in done if d) or "maintenance recorded"


def open_faults(events, maintenance, machine: str | None = None) -> list[dict]:
    """The faults among a print's alarms that no maintenance recorded since has closed.

    Parameters
    ----------
    events : iterable of dict or AnomalyEvent
        The print's alarms (``cause``, ``onset_s``).
    maintenance : list of dict
        The maintenance events recorded after the print (``nozzle_cleaned``,
        ``vial_refilled_ml``, ``note`` …, as ``ajtwin machine maintain`` stores them).
    machine : str, optional
        The machine's name, for the command in the action.

    Returns
    -------
    One dict per open fault, first onset first: ``cause``, ``onset_s`` and ``sentence``
    (:func:`alarm_sentence`: the cause in words, since when, what to do).

    Examples
    --------
    >>> [f["cause"] for f in open_faults([{"cause": "nozzle_clog", "onset_s": 60.0}], [])]
    ['nozzle_clog']
    >>> open_faults([{"cause": "nozzle_clog", "onset_s": 60.0}], [{"nozzle_cleaned": True}])
    []
    """
    table = _advice()["causes"]
    found: dict[str, float] = {}
    for ev in events:
        ev = ev if isinstance(ev, dict) else {"cause": ev.cause, "onset_s": ev.onset_s}
        cause = str(ev["cause"])
        entry = table.get(cause)
        if entry is None or not entry["fault"]:
            continue
        if closing_maintenance(cause, maintenance) is None:
            found[cause] = min(found.get(cause, np.inf), float(ev["onset_s"]))
    return [
        {"cause": cause, "onset_s": onset, "sentence": alarm_sentence(cause, onset, machine)}
        for cause, onset in sorted(found.items(), key=lambda item: item[1])
    ]


def print_status(stored_status: str, causes, mismatch: bool = False) -> str:
    """A print's status as ``ajtwin machine history`` shows it: what its alarms were
    (``clog``, ``carrier leak`` …) and ``mismatch`` when the model did not fit the machine;
    ``ok`` only for a print in the chain with neither; a print out of the chain says so
    first (``dropped: clog``).

    >>> print_status("ok", ["nozzle_clog"]), print_status("ok", [], True), print_status("ok", [])
    ('clog', 'mismatch', 'ok')
    >>> print_status("dropped", ["nozzle_clog", "carrier_leak"])
    'dropped: clog, carrier leak'
    """
    table = _advice()["causes"]
    words = []
    for cause in causes:
        entry = table.get(str(cause))
        word = entry["status"] if entry else str(cause).replace("_", " ")
        if word not in words:
            words.append(word)
    if mismatch and table["model_machine_mismatch"]["status"] not in words:
        words.append(table["model_machine_mismatch"]["status"])
    found = ", ".join(words)
    if stored_status == "ok":
        return found or "ok"
    return f"{stored_status}: {found}" if found else str(stored_status)


def alarm_lines(alarm, machine: str | None = None, closed_by: str | None = None) -> list[str]:
    """An alarm as the commands print it, times in minutes past the print's start: when it
    was raised and began, its likely cause, what to do (or, ``closed_by``, the maintenance
    that closed the fault since), and the detectors in words.

    ``alarm``: an :class:`~ajtwin.apps.detection.streaming.AnomalyEvent` or a dict with
    ``detected_s``, ``onset_s``, ``cause``, ``description``, ``detectors`` (a list or a
    comma-separated string, as the registry keeps them).

    >>> alarm_lines({"detected_s": 3640, "onset_s": 3604, "cause": "nozzle_clog",
    ...              "description": "nozzle clog", "detectors": "cusum+ P_c"})[0]
    'alarm at 60.7 min (onset ≈ 60.1 min): nozzle clog'
    """
    get = alarm.get if isinstance(alarm, dict) else lambda key: getattr(alarm, key)
    detectors = get("detectors") or ()
    if isinstance(detectors, str):
        detectors = [d.strip() for d in detectors.split(",") if d.strip()]
    onset = float(get("onset_s"))
    lines = [
        f"alarm at {units.minutes_text(float(get('detected_s')))} (onset ≈ "
        f"{units.minutes_text(onset)}): {get('description')}"
    ]
    action = cause_action(get("cause"), machine)
    if closed_by:
        lines.append(f"  closed: {closed_by}")
    elif action:
        lines.append(f"  what to do: {action}")
    if detectors:
        lines.append(f"  seen as: {'; '.join(detector_words(d) for d in detectors)}")
    return lines
