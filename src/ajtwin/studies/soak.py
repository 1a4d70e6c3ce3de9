"""Long runs of the twin over the virtual printer: numerical health, memory, speed.

Two soaks ("Long runs"):

* :func:`soak_print` — one long virtual print (hours to a week) through the twin, fed
  to it in consecutive chunks as a streaming engine would (each chunk starts from the
  previous chunk's end state and θ, the whole print is never held twice). After every
  chunk it checks every step's covariance (finite, symmetric, positive definite: the
  smallest eigenvalue of the correlation matrix), the means (finite, inside the physical
  range of :class:`~ajtwin.model.limits.StateLimits`), θ (finite, |θ| / prior σ), counts
  the divergence guard's firings, and records CPU time and resident memory (VmRSS,
  VmHWM from ``/proc/self/status``). Days are simulated one by one with
  ``continue_from`` (the atomizer restarts each day, the vial and deposits carry on).
* :func:`soak_machine` — many short prints of one machine back to back through the
  registry (:func:`ajtwin.engine.ingest.ingest_record`): the chain carries the state and
  θ; records per print the end state, θ and the time ``machine history``/``machine show``
  take as the registry grows.

Example
-------
Not run in the suite: 12 min of print through the twin a chunk at a time (a minute or more).

>>> rep = soak_print(hours=0.2, chunk_min=6)  # doctest: +SKIP
>>> rep.healthy, rep.guard_firings  # doctest: +SKIP
(True, 0)
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin.engine.chain import carry_over, state_limits
from ajtwin.engine.ingest import ingest_record
from ajtwin.estimation import Twin
from ajtwin.simulation import simulate
from ajtwin.store.registry import Registry


def memory_mb() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process [MB] from /proc/self/status (NaN elsewhere)."""
    values = {"VmRSS": float("nan"), "VmHWM": float("nan")}
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                key = line.split(":")[0]
                if key in values:
                    values[key] = float(line.split()[1]) / 1024.0  # kB → MB
    except OSError:
        pass
    return values["VmRSS"], values["VmHWM"]


def covariance_health(covs) -> dict:
    """Worst symmetry error and smallest correlation-matrix eigenvalue of P (T, 5, 5)."""
    p = np.asarray(covs, dtype=float)
    finite = bool(np.all(np.isfinite(p)))
    if not finite:
        return {"finite": False, "max_asymmetry": np.inf, "min_corr_eig": -np.inf}
    diag = np.sqrt(np.clip(np.diagonal(p, 0, 1, 2), 1e-300, None))
    corr = p / (diag[:, :, None] * diag[:, None, :])
    asym = np.abs(corr - np.swapaxes(corr, 1, 2)).max()
    # scale-free: P is SPD iff its correlation matrix is (states span 1e-7 .. 1e0)
    eig = np.linalg.eigvalsh(0.5 * (corr + np.swapaxes(corr, 1, 2)))
    return {"finite": True, "max_asymmetry": float(asym), "min_corr_eig": float(eig.min())}


@dataclass
class SoakReport:
    """One row per chunk (``chunks``) and the verdicts over the whole run."""

    hours: float
    chunk_min: float
    chunks: list = field(default_factory=list)
    guard_steps: list = field(default_factory=list)  # print time [s] of each guard firing

    @property
    def guard_firings(self) -> int:
        """Steps at which the divergence guard reset the filter."""
        return len(self.guard_steps)

    @property
    def healthy(self) -> bool:
        """Every chunk finite, symmetric, positive definite, physical and with a finite θ."""
        return all(
            c["finite"] and c["max_asymmetry"] < 1e-9 and c["min_corr_eig"] > 0
            and c["means_physical"] and c["theta_finite"]
            for c in self.chunks
        )  # fmt: skip

    def table(self):
        """One row per chunk of the soak."""
        return pd.DataFrame(self.chunks)


def soak_print(
    hours: float = 24.0,
    *,
    chunk_min: float = 60.0,
    scenario: str = "exp1",
    seed: int = 0,
    day_min: float = 1440.0,
    progress=None,
) -> SoakReport:
    """Run the twin over a ``hours``-long virtual print in chunks (see module docstring).

    Parameters
    ----------
    hours : float
        Length of the virtual print [h].
    chunk_min : float
        Twin chunk [min]; a multiple of the EM cadence (5 min) keeps EM's rhythm.
    day_min : float
        The virtual printer is simulated in pieces of this length [min] (memory).
    progress : callable(hours_done, chunk_row), optional

    Returns
    -------
    SoakReport
    """

    twin = Twin.default()
    prior_std = np.asarray(twin.config.theta_prior_std, dtype=float)
    limits = state_limits()
    report = SoakReport(hours, chunk_min)
    total_s = int(round(hours * 3600))
    chunk_s = max(int(round(chunk_min * 60)), 2)
    state = None
    previous = None
    done_s = 0
    day = 0
    while done_s < total_s:
        day_s = min(int(round(day_min * 60)), total_s - done_s)
        record = simulate(scenario, seed=seed + day, duration_min=day_s / 60.0,
                          continue_from=previous)  # fmt: skip
        if state is not None:  # a new day is a new atomizer run (as between prints)
            state = carry_over(*state)
        inputs, outputs = record.inputs, record.outputs
        for pos in range(0, day_s, chunk_s):
            end = min(pos + chunk_s, day_s)
            if end - pos < 2:
                break
            cpu0 = time.process_time()
            run = twin.run(inputs=inputs[pos:end], measurements=outputs[pos:end], start=state)
            cpu = time.process_time() - cpu0
            f = run.filtered
            covs = np.asarray(f.covariances)
            means = np.asarray(f.means)
            state = (np.asarray(run.end_mean), np.asarray(run.end_cov))
            fired = np.flatnonzero(np.asarray(f.reinitialised))
            report.guard_steps += (done_s + pos + fired).tolist()
            rss, hwm = memory_mb()
            theta = np.asarray(run.theta_per_step)
            row = {
                "hour_end": (done_s + end) / 3600.0,
                "cpu_s": cpu,
                "cpu_s_per_hour": cpu / ((end - pos) / 3600.0),
                "rss_mb": rss,
                "hwm_mb": hwm,
                **covariance_health(covs),
                "means_physical": bool(limits.inside(means).all()),
                "theta_finite": bool(np.all(np.isfinite(theta))),
                "max_theta_over_prior": float(np.max(np.abs(theta) / prior_std)),
                "guard_firings": int(fired.size),
                "mean_nis": float(np.nanmean(np.asarray(f.nis))),
                **{f"end_{i}": float(v) for i, v in enumerate(run.end_mean)},
                **{f"std_{i}": float(v) for i, v in enumerate(np.sqrt(np.diag(run.end_cov)))},
                **{f"true_{i}": float(v) for i, v in enumerate(record.true_states[end - 1])},
            }
            report.chunks.append(row)
            del run, f, covs, means
            if progress:
                progress((done_s + end) / 3600.0, row)
        previous = record
        done_s += day_s
        day += 1
    return report


def soak_machine(
    n_prints: int,
    *,
    print_min: float = 3.0,
    store=None,
    scenario: str = "exp1",
    seed: int = 0,
    twin_overrides: dict | None = None,
    progress=None,
):
    """Ingest ``n_prints`` short virtual prints of one machine into a registry.

    ``twin_overrides`` go to the twin's config (e.g. a short EM window so that θ is
    learned within short prints and its carry-over is exercised).

    Each print continues the virtual machine (``continue_from``): the vial and deposits
    carry on in the truth, as the chain carries them in the twin.

    Returns
    -------
    DataFrame, one row per print: end state, truth, θ, status, ingest CPU time, and the
    CPU time of ``history`` and ``machine`` + ``last_print`` (what ``machine show`` reads)
    right after it.
    """

    folder = None
    if store is None:
        folder = tempfile.TemporaryDirectory(prefix="ajtwin-soak-")
        store = Path(folder.name) / "soak.sqlite"
    reg = Registry(store)
    reg.add_machine("soak")
    rows = []
    previous = None
    try:
        for i in range(n_prints):
            record = simulate(scenario, seed=seed + i, duration_min=print_min,
                              continue_from=previous)  # fmt: skip
            record.meta["machine_id"] = "soak"
            cpu0 = time.process_time()
            result = ingest_record(
                reg, "soak", record, source=f"virtual print {i + 1}", twin_overrides=twin_overrides
            )
            cpu_ingest = time.process_time() - cpu0
            cpu0 = time.process_time()
            reg.history("soak")
            cpu_history = time.process_time() - cpu0
            cpu0 = time.process_time()
            reg.machine("soak")
            reg.last_print("soak")
            reg.anomalies("soak")
            cpu_show = time.process_time() - cpu0
            p = reg.get_print(result.print_id)
            rows.append(
                {
                    "seq": result.seq,
                    "status": p["status"],
                    "started_from": result.summary.get("started_from"),
                    "cpu_ingest_s": cpu_ingest,
                    "cpu_history_s": cpu_history,
                    "cpu_show_s": cpu_show,
                    "anomalies": len(result.events),
                    **{f"end_{k}": float(v) for k, v in enumerate(p["end_mean"])},
                    **{f"true_{k}": float(v) for k, v in enumerate(record.true_states[-1])},
                    **{f"theta_{k}": float(v) for k, v in enumerate(p["theta_after"])},
                }
            )
            if progress:
                progress(i + 1, rows[-1])
            previous = record
    finally:
        reg.close()
        if folder is not None:
            folder.cleanup()
    return pd.DataFrame(rows)
