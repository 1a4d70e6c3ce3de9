"""The print chain: which stored print the next print of a machine starts from.

A machine's twin carries its state and θ from print to print. One bad print (wrong
units, a sensor stuck at a plausible-looking value) can drive the estimate to a state no
printer can be in — a negative vial volume, a 534 µm droplet — and the next clean print
would start from it (V_l 0.036 mL, ΔR_N 7.97 µm, a false "ink running out"). The rules
here stop that:

* a print any of whose estimated states (any step, the start or the end) leaves the
  physical range of :class:`ajtwin.model.limits.StateLimits` is stored **excluded**, with
  the reason (:func:`judge_run`);
* the next print starts from the end state and θ of the newest print in the chain
  (``status = 'ok'`` and an end state inside the range), else from the initial-state fit
  with the nominal θ (:func:`chain_start`);
* ``ajtwin machine drop NAME --print SEQ`` takes a print out of the chain by hand
  (kept for history), ``ajtwin machine restore`` puts it back.

Between prints the fast states restart (a new atomizer run: droplet size and aerosol
fraction re-equilibrate within seconds to minutes), so their carried-over variance is
widened by :data:`BETWEEN_PRINT_STD`; V_l, ΔR_T and ΔR_N carry over as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ajtwin.model.limits import StateLimits
from ajtwin.store.registry import STATUS_EXCLUDED, STATUS_OK, Registry

#: σ added between prints to d_a [µm] and φ_A [relative]; others carry over unchanged.
BETWEEN_PRINT_STD = {"droplet_diameter_um": 0.2, "aerosol_fraction_relative": 0.2}


@lru_cache(maxsize=1)
def state_limits():
    """The shared physical state range (``data/state_limits.toml``), loaded once."""
    return StateLimits.default()


def state_violations(x) -> list[str]:
    """Messages for the states of one x (5,) outside the physical range (empty: fine)."""
    return state_limits().violations(np.asarray(x, dtype=float).reshape(-1))


def open_registry(path=None, **kwargs) -> Registry:
    """The registry at ``path`` (:class:`~ajtwin.store.registry.Registry` keywords), whose
    migration from version 1 takes prints that end in an impossible state out of the chain
    (:func:`state_violations`)."""
    return Registry(path, end_state_check=state_violations, **kwargs)


def carry_over(end_mean, end_cov) -> tuple[np.ndarray, np.ndarray]:
    """Start state of the next print from the previous end state (see module docstring)."""
    mean = np.asarray(end_mean, dtype=float).copy()
    cov = np.asarray(end_cov, dtype=float).copy()
    cov[0, 0] += BETWEEN_PRINT_STD["droplet_diameter_um"] ** 2
    cov[4, 4] += (BETWEEN_PRINT_STD["aerosol_fraction_relative"] * mean[4]) ** 2
    return mean, cov


@dataclass
class ChainStart:
    """Where the next print starts.

    Attributes
    ----------
    start : (mean (5,), cov (5, 5)) or None
        None: the initial-state fit of the print itself.
    theta : (5,) or None
        θ to start with (None: the twin's nominal θ).
    from_seq : int or None
        The print it carries over from.
    latest_seq : int or None
        The machine's newest print, in the chain or not (the ingest's stale-start check).
    skipped : list of str
        Prints passed over and why (said to the user).
    """

    start: tuple | None
    theta: np.ndarray | None
    from_seq: int | None
    latest_seq: int | None
    skipped: list

    @property
    def description(self) -> str:
        """Where the print starts, in words (and the prints passed over, and why)."""
        text = "initial fit" if self.from_seq is None else f"print {self.from_seq}"
        if self.skipped:
            text += " (skipped " + "; ".join(self.skipped) + ")"
        return text


def chain_start(registry, machine: str, below_seq: int | None = None) -> ChainStart:
    """The start of ``machine``'s next print: the newest good print's end, else the fit
    (``below_seq``: of print ``below_seq``, from the prints before it)."""
    if below_seq is None:
        latest = registry.last_print(machine, in_chain=False)
    else:
        latest = registry.print_by_seq(machine, below_seq - 1) if below_seq > 1 else None
    skipped = []
    if latest is not None and latest["status"] != STATUS_OK:
        skipped.append(f"print {latest['seq']}: {latest['status']}")
    for p in registry.chain_prints(machine, below_seq):
        problems = state_violations(p["end_mean"]) + _bad_covariance(p["end_cov"])
        problems += [] if np.all(np.isfinite(p["theta_after"])) else ["θ not finite"]
        if problems:  # stored before the range check (or by hand): never a start
            skipped.append(f"print {p['seq']}: {'; '.join(problems)}")
            continue
        return ChainStart(
            carry_over(p["end_mean"], p["end_cov"]),
            np.asarray(p["theta_after"], dtype=float),
            int(p["seq"]),
            None if latest is None else int(latest["seq"]),
            skipped,
        )
    return ChainStart(None, None, None, None if latest is None else int(latest["seq"]), skipped)


def _bad_covariance(cov) -> list[str]:
    cov = np.asarray(cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        return ["end covariance not finite"]
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=0.0):
        return ["end covariance not symmetric"]
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return ["end covariance not positive definite"]
    return []


def judge_run(run) -> tuple[str, str]:
    """(status, reason) of a twin run: ``excluded`` when any estimated state (start, any
    step, end) is outside the physical range or not finite, else ``ok``."""
    limits = state_limits()
    means = np.asarray(run.means, dtype=float)
    for label, x in (("start", run.start_mean), ("end", run.end_mean)):
        problems = limits.violations(x)
        if problems:
            return STATUS_EXCLUDED, f"{label} state: " + "; ".join(problems)
    first = limits.first_violation_index(means)
    if first is not None:
        t = float(np.asarray(run.time_s)[first])
        return STATUS_EXCLUDED, f"state at {t:.0f} s: " + "; ".join(limits.violations(means[first]))
    problems = _bad_covariance(run.end_cov)
    if problems:
        return STATUS_EXCLUDED, "; ".join(problems)
    return STATUS_OK, ""
