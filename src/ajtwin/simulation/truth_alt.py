"""A second, structurally different truth generator — for evaluation only.

The first generator (:mod:`ajtwin.simulation.truth`) tuned the twin (noise.toml, the
detector and guard thresholds). Figures claimed for real machines are measured on this
one, which tuned nothing (docs/explanation/per-machine-calibration.md). Selected by
``--truth alt``; its
constants live in ``data/truth_alt.toml``. What differs:

* **droplet size d_a** — a random walk with Poisson jumps (atomizer mode hops) plus a
  response to Q_c and I_A through two cascaded first-order lags, instead of an OU wander,
  a levelling trend and one lag;
* **generation** — the atomizer efficiency is a slow sinusoid plus a seeded linear
  trend, instead of an OU wander;
* **deposition laws** — the tube and nozzle deposits grow as the model's rate at the
  reference droplet size times (d_a/3.5 µm)^p (impaction-like, p = 2 and 3), instead of
  the model's settling/diffusion size dependence times a constant;
* **integration** — RK2 (midpoint) sub-steps, not RK4;
* **noise** — Student-t line noise (heavy tails), AR(1) pressure noise (slow gauge
  wander), Gaussian Q_m noise, instead of log-normal and white noise.

A third atomizer, the **off-model atomizer** (``[atomizer_variant]``): a machine whose
atomizer delivers a constant 0.7–1.3 × the generation model H (drawn per machine,
:func:`off_model_atomizer_machine`) and whose efficiency drifts by up to ±12 % per hour
in each print (:func:`apply_machine_atomizer`). Only on this generator: it is evaluation,
never tuning.

Faults (clog, leak, dropout, pressure drift), the MFC layer, the machine deviation and
the output model g are shared with the first generator: a fault is the same fault.

Examples
--------
>>> from ajtwin.simulation.printer import run_virtual_print
>>> vp = run_virtual_print("exp1", seed=1, duration_min=1.0, truth_generator="alt")
>>> vp.record.meta["truth_generator"]
'alt'
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.signal import lfilter

from ajtwin import units
from ajtwin._jax import jax, jnp
from ajtwin.config import packaged_toml
from ajtwin.model.line_speed import load_line_speed_law
from ajtwin.model.system import output_function
from ajtwin.simulation.machine import draw_machine
from ajtwin.simulation.startup import apply_startup
from ajtwin.simulation.truth import truth_rates

CHUNK_S = 600


def load_alt_settings() -> dict:
    """The second generator's settings with their provenance (``data/truth_alt.toml``)."""
    return packaged_toml("data/truth_alt.toml")


def lag_filter(signal: np.ndarray, tau_s: float) -> np.ndarray:
    """The second generator's first-order lag: y_k = (1 − b) y_{k−1} + b signal_k,
    b = 1 − e^{−1/τ} [τ in s], starting in equilibrium with ``signal[0]``."""
    b = 1.0 - np.exp(-1.0 / tau_s)
    y, _ = lfilter([b], [1.0, -(1.0 - b)], signal, zi=[(1.0 - b) * signal[0]])
    return y


def alt_processes(scenario, processes, seed: int, settings: dict | None = None):
    """Replace the droplet-size and generation processes of ``processes`` (in place).

    Faults of the scenario keep acting: an atomizer dropout scales the new generation,
    a clog raises the nozzle factor column as before.
    """
    cfg = settings or load_alt_settings()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7001]))
    n = len(processes.droplet_um)
    t = np.arange(n, dtype=float)
    d = cfg["droplet"]
    base = scenario.config["truth"]
    start = base["droplet_median_um"] + d["offset_sd_um"] * rng.standard_normal()
    walk = np.cumsum(rng.standard_normal(n)) * d["walk_sd_um_per_sqrt_h"] / np.sqrt(3600.0)
    jumps = rng.random(n) < d["jump_rate_per_h"] / 3600.0
    walk += np.cumsum(np.where(jumps, rng.standard_normal(n) * d["jump_sd_um"], 0.0))
    target = d["carrier_um_per_sccm"] * (processes.mfc_inputs[:, 1] - 23.0) + d[
        "current_um_per_mA"
    ] * (processes.mfc_inputs[:, 0] - 375.0)
    response = lag_filter(lag_filter(target, d["lag_s"][0]), d["lag_s"][1])
    processes.droplet_um = np.maximum(start + walk + response, 0.5)

    g = cfg["generation"]
    offset = g["offset_sd"] * rng.standard_normal()
    phase = rng.uniform(0, 2 * np.pi)
    trend = g["trend_per_h_sd"] * rng.standard_normal()
    efficiency = (
        (1.0 + offset)
        * (1.0 + g["amplitude"] * np.sin(2 * np.pi * t / (g["period_min"] * 60.0) + phase))
        * np.maximum(1.0 + trend * t / 3600.0, 0.0)
    )
    fault = scenario.config["fault"]
    if fault["kind"] == "atomizer_dropout":
        onset = scenario.fault_onset_s
        duration = float(fault["duration_min"]) * 60.0
        active = (t >= onset) if duration <= 0 else (t >= onset) & (t < onset + duration)
        efficiency = np.where(active, efficiency * float(fault["generation_fraction"]), efficiency)
    drivers = processes.drivers.copy()
    drivers[:, 0] = efficiency
    # the scenario's factors (and a clog's multiplier) relative to their first value
    drivers[:, 1] = drivers[:, 1] / drivers[0, 1] * cfg["deposition"]["tube_factor"]
    drivers[:, 2] = drivers[:, 2] / drivers[0, 2] * cfg["deposition"]["nozzle_factor"]
    processes.drivers = drivers
    processes.draws = {
        **processes.draws,
        "alt_droplet_start_um": float(start),
        "alt_generation_offset": float(offset),
        "alt_generation_trend_per_h": float(trend),
        "alt_droplet_jumps": int(jumps.sum()),
    }
    # the start-up again on the replaced droplet size and generation (its own stream)
    startup_rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7005]))
    return apply_startup(processes, scenario.config["startup"], startup_rng)


def off_model_atomizer_machine(machine_seed: int, machine=None, settings: dict | None = None):
    """A virtual machine whose atomizer is not the generation model (evaluation only).

    Parameters
    ----------
    machine_seed : int
        Draws the atomizer's output factor, uniform in 1 + ``output_range`` of
        ``[atomizer_variant]``, from its own stream of the seed.
    machine : MachineDeviation, optional
        The machine's other deviations (default: :func:`~ajtwin.simulation.machine.draw_machine`
        of the same seed, so the plumbing, gauges and lines are those of ``--seeds`` alone).

    Examples
    --------
    >>> m = off_model_atomizer_machine(1201)
    >>> 0.7 <= m.atomizer_output <= 1.3, m.atomizer_wander_per_h
    (True, 0.12)
    """
    cfg = (settings or load_alt_settings())["atomizer_variant"]
    machine = draw_machine(int(machine_seed)) if machine is None else machine
    rng = np.random.default_rng(np.random.SeedSequence([int(machine_seed), 7003]))
    low, high = (float(v) for v in cfg["output_range"])
    return replace(
        machine,
        name=f"{machine.name}-atomizer",
        atomizer_output=float(1.0 + rng.uniform(low, high)),
        atomizer_wander_per_h=float(cfg["wander_per_h"]),
    )


def apply_machine_atomizer(processes, machine, seed: int):
    """Scale the generation driver of ``processes`` by the machine's atomizer (in place).

    efficiency ← efficiency · a · (1 + r t/3600), with a the machine's
    ``atomizer_output`` and r a trend drawn per print uniformly from
    ±``atomizer_wander_per_h`` (its own stream of the print ``seed``).
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7004]))
    wander = float(machine.atomizer_wander_per_h)
    trend = float(rng.uniform(-wander, wander)) if wander > 0 else 0.0
    t = np.arange(len(processes.drivers), dtype=float)
    drivers = processes.drivers.copy()
    factor = machine.atomizer_output * np.maximum(1.0 + trend * t / 3600.0, 0.0)
    drivers[:, 0] = drivers[:, 0] * factor
    processes.drivers = drivers
    processes.draws = {
        **processes.draws,
        "atomizer_output": float(machine.atomizer_output),
        "atomizer_trend_per_h": trend,
    }
    return processes


def alt_rates(x, flow_input, drivers, params, deposition):
    """Rates of the alternative truth: the first generator's vial and φ_A balance, but
    deposits ∝ (model rate at d_ref) · (d_a/d_ref)^p."""
    reference, tube_p, nozzle_p = deposition
    unit = drivers.at[1].set(1.0).at[2].set(1.0)
    rates, _ = truth_rates(x, flow_input, unit, params)
    at_reference, _ = truth_rates(x.at[0].set(reference), flow_input, unit, params)
    ratio = x[0] / reference
    d_tube = drivers[1] * at_reference[2] * ratio**tube_p
    d_nozzle = drivers[2] * at_reference[3] * ratio**nozzle_p
    rates = rates.at[2].set(d_tube).at[3].set(d_nozzle)
    out_of_vial = x[4] * units.sccm_to_ml_per_s(flow_input[1])
    tube_radius = params.tube_radius - units.um_to_m(x[2])
    nozzle_radius = params.nozzle_radius - units.um_to_m(x[3])
    into_tube = units.m3_to_ml(
        2 * jnp.pi * tube_radius * params.tube_length * units.um_to_m(d_tube)
    )
    into_nozzle = units.m3_to_ml(
        2 * jnp.pi * nozzle_radius * params.nozzle_length * units.um_to_m(d_nozzle)
    )
    return rates, out_of_vial - into_tube - into_nozzle


def _scan(carry, droplet, droplet_next, flows, drivers, params, coefficients, deposition, substeps):
    dt = 1.0 / substeps

    def body(carry, per_second):
        x, substrate = carry
        d_a, flow, driver, d_next = per_second
        x = x.at[0].set(d_a)
        out = (x, substrate, output_function(x, flow, params, coefficients))

        def sub(c, _):
            xs, ss = c
            k1, s1 = alt_rates(xs, flow, driver, params, deposition)
            k2, s2 = alt_rates(xs + 0.5 * dt * k1, flow, driver, params, deposition)
            return (xs + dt * k2, ss + dt * s2), None

        (x, substrate), _ = jax.lax.scan(sub, (x, substrate), None, length=substeps)
        return (x.at[0].set(d_next), substrate), out

    return jax.lax.scan(body, carry, (droplet, flows, drivers, droplet_next))


#: The alternative truth over a run of seconds, compiled; shared by
#: :func:`integrate_alt_truth` (a whole print) and the stepper (a print second by second).
scan_alt_seconds = jax.jit(_scan, static_argnames=("substeps",))


def integrate_alt_truth(x0, droplet_um, flow_inputs, drivers, params, coefficients, settings=None):
    """States (T, 5), substrate ink (T,), noise-free outputs (T, 5) of the alternative truth."""
    cfg = settings or load_alt_settings()
    dep = cfg["deposition"]
    deposition = (
        float(dep["reference_um"]),
        float(dep["tube_size_exponent"]),
        float(dep["nozzle_size_exponent"]),
    )
    substeps = int(cfg["measurement"]["substeps"])
    droplet_um = np.asarray(droplet_um, float)
    n = len(droplet_um)
    droplet_next = np.concatenate([droplet_um[1:], droplet_um[-1:]])
    pad = (-n) % CHUNK_S

    def padded(a):
        return np.concatenate([a, np.repeat(a[-1:], pad, axis=0)]) if pad else a

    arrays = [
        padded(np.asarray(a, float)) for a in (droplet_um, droplet_next, flow_inputs, drivers)
    ]
    carry = (jnp.asarray(x0, dtype=float), jnp.zeros(()))
    coefficients = jnp.asarray(coefficients, dtype=float)
    pieces = []
    for start in range(0, n + pad, CHUNK_S):
        chunk = [a[start : start + CHUNK_S] for a in arrays]
        carry, emitted = scan_alt_seconds(
            carry, *chunk, params, coefficients, deposition, substeps=substeps
        )
        pieces.append([np.asarray(e) for e in emitted])
    names = ("states", "substrate_ink_mL", "outputs")
    return {name: np.concatenate([p[i] for p in pieces])[:n] for i, name in enumerate(names)}


def alt_measure(scenario, processes, outputs_true, seed: int, settings=None):
    """Measured inputs and outputs with the alternative noise shapes (module docstring)."""
    cfg = (settings or load_alt_settings())["measurement"]
    meas = scenario.config["measurement"]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7002]))
    n = len(outputs_true)
    sensor = np.stack(
        [
            rng.standard_normal(n) * meas["current_sensor_noise_mA"],
            rng.standard_normal(n) * meas["flow_sensor_noise_sccm"],
            rng.standard_normal(n) * meas["flow_sensor_noise_sccm"],
        ],
        axis=-1,
    )
    inputs = processes.mfc_inputs + sensor
    y = np.array(outputs_true, dtype=float)
    dof = float(cfg["line_t_dof"])
    y[:, 0] *= 1.0 + cfg["linewidth_sd"] * rng.standard_t(dof, n)
    y[:, 1] *= np.maximum(1.0 + cfg["overspray_sd"] * rng.standard_t(dof, n), 0.05)
    y[:, 1] = np.maximum(y[:, 1], 0.0)  # as measure(): no negative overspray on camera
    a = float(cfg["pressure_ar"])
    for j in (2, 3):
        white = rng.standard_normal(n) * cfg["pressure_sd_Pa"] * np.sqrt(1 - a**2)
        y[:, j] += lfilter([1.0], [1.0, -a], white)
    y[:, 2:4] += processes.pressure_drift_pa
    y[:, 4] *= np.maximum(1.0 + cfg["material_flow_sd"] * rng.standard_normal(n), 0.05)
    missing = rng.random((n, 4))
    y[missing[:, 0] < meas["line_missing_fraction"], 0:2] = np.nan
    y[missing[:, 1] < meas["pressure_missing_fraction"], 2] = np.nan
    y[missing[:, 2] < meas["pressure_missing_fraction"], 3] = np.nan
    y[missing[:, 3] < meas["material_flow_missing_fraction"], 4] = np.nan
    return inputs, y


def draw_alt_line_speed(rng: np.random.Generator, settings: dict | None = None) -> dict:
    """The alternative truth's speed law, drawn: a beam footprint plus a √A-spreading bead.

    Returns a JSON-ready dict (``form``, ``beam_fraction``, ``spreading_exponent``, and the
    reference speed and validity range of ``data/line_speed.toml``), for
    :func:`alt_line_speed_factors` and the record's ``truth_draws``.
    """

    cfg = (settings or load_alt_settings())["line_speed"]
    low, high = (float(v) for v in cfg["beam_fraction_range"])
    law = load_line_speed_law()
    return {
        "form": "beam_plus_spreading",
        "beam_fraction": float(rng.uniform(low, high)),
        "spreading_exponent": float(cfg["spreading_exponent"]),
        "reference_speed_mm_s": float(law.reference_speed_mm_s),
        "min_speed_mm_s": float(law.min_speed_mm_s),
        "max_speed_mm_s": float(law.max_speed_mm_s),
    }


def alt_line_speed_factors(platen_speed_mm_s, law: dict):
    """(f_w, f_o) of the alternative truth at speeds ν [mm/s] (NumPy arrays).

    f_w = φ + (1 − φ)(ν_ref/ν)^p with ν clipped to the validity range; f_o = 1 (overspray
    does not depend on the speed). Both are 1 at ν_ref.
    """
    nu = np.clip(
        np.asarray(platen_speed_mm_s, dtype=float), law["min_speed_mm_s"], law["max_speed_mm_s"]
    )
    phi = law["beam_fraction"]
    spreading = np.power(law["reference_speed_mm_s"] / nu, law["spreading_exponent"])
    return phi + (1.0 - phi) * spreading, np.ones_like(nu)
