"""The atomizer's start-up: the mist building up and the droplets settling after switch-on.

An AJ system needs a run-in of 5-15 min after the atomizer is switched on before its jet is
steady (commonly reported; e.g. Karlsruhe Institute of Technology's account of conventional
aerosol jet print heads, which need "anywhere from five to fifteen minutes" of run-in). The
virtual printer models it, when a scenario's ``[startup]`` asks for it (off by default), as

    generation × [1 − (1 − g_0) e^{−t/τ}],    d_a + δ e^{−t/τ},

g_0 the output at switch-on (uniform in [initial_output_low, initial_output_high]), δ the
droplets' excess at switch-on (uniform in [0, droplet_offset_um]), τ set so that the
generation is within 2 % of its level at t_s = τ ln((1 − g_0)/0.02), t_s uniform in
[settling_min_low, settling_min_high] minutes. Both generators use it.

Examples
--------
>>> cfg = {"settling_min_low": 5.0, "settling_min_high": 15.0, "initial_output_low": 0.2,
...        "initial_output_high": 0.6, "droplet_offset_um": 0.3}
>>> gen, shift, draws = startup_transient(cfg, np.random.default_rng(0), np.arange(3600.0))
>>> settle = draws["startup_settling_s"]
>>> bool(abs(gen[int(settle)] - 0.98) < 1e-3), 5 * 60 <= settle <= 15 * 60
(True, True)
"""

from __future__ import annotations

import numpy as np

#: the generation's distance to its level at the drawn settling time t_s
SETTLED_WITHIN = 0.02


def startup_enabled(cfg: dict) -> bool:
    """Whether a scenario's ``[startup]`` asks for a start-up transient."""
    return float(cfg.get("settling_min_high", 0.0)) > 0.0


def startup_transient(cfg: dict, rng: np.random.Generator, t) -> tuple:
    """(generation factor (T,), droplet shift (T,) [µm], draws) at times t [s]."""
    t = np.asarray(t, dtype=float)
    settle_s = 60.0 * rng.uniform(cfg["settling_min_low"], cfg["settling_min_high"])
    initial = rng.uniform(cfg["initial_output_low"], cfg["initial_output_high"])
    excess = rng.uniform(0.0, cfg["droplet_offset_um"])
    tau = settle_s / np.log((1.0 - initial) / SETTLED_WITHIN)
    decay = np.exp(-t / tau)
    draws = {
        "startup_settling_s": float(settle_s),
        "startup_initial_output": float(initial),
        "startup_droplet_excess_um": float(excess),
        "startup_time_constant_s": float(tau),
    }
    return 1.0 - (1.0 - initial) * decay, excess * decay, draws


def apply_startup(processes, cfg: dict, rng: np.random.Generator):
    """Processes with the start-up transient (in place; unchanged when it is off)."""
    if not startup_enabled(cfg):
        return processes
    t = np.arange(len(processes.droplet_um), dtype=float)
    generation, shift, draws = startup_transient(cfg, rng, t)
    drivers = processes.drivers.copy()
    drivers[:, 0] = drivers[:, 0] * generation
    processes.drivers = drivers
    processes.droplet_um = processes.droplet_um + shift
    processes.draws = {**processes.draws, **draws}
    return processes
