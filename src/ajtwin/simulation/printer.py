"""The virtual AJ printer: scenario + seed → print record with known truth.

Three layers, all seeded from one integer:

1. exogenous processes drawn with NumPy (:func:`draw_processes`): MFC and current
   jitter, the droplet-size process, generation wander, deposition factors, faults;
2. the true dynamics, a pure JAX ``lax.scan`` (:mod:`ajtwin.simulation.truth`);
3. the measurement layer (:func:`measure`): what the MFCs, the pressure sensors,
   the alignment camera and the height-profile CNN report — jitter, noise, sensor
   drift, log-normal line noise, missing samples.

Same scenario and seed → the same record, bit for bit. Each random process has
its own stream (``SeedSequence(seed).spawn``), so two scenarios run with one seed
share their realisation up to a fault's onset — handy for anomaly detection.

Examples
--------
>>> rec = simulate("exp1", seed=0, duration_min=1.0)
>>> rec.data.shape, rec.meta["scenario"]
((60, 14), 'exp1')
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import lfilter

from ajtwin import __version__, units
from ajtwin.io.records import (
    INPUT_COLUMNS,
    OUTPUT_COLUMNS,
    RECORD_COLUMNS,
    TIME_COLUMN,
    TRUTH_COLUMNS,
    UNITS,
    PrintRecord,
)
from ajtwin.model import coefficient_matrix, load_output_coefficients, load_parameters
from ajtwin.model.system import output_function, steady_aerosol_fraction
from ajtwin.simulation.machine import MachineDeviation, resolve_machine
from ajtwin.simulation.scenarios import Scenario, load_scenario
from ajtwin.simulation.startup import apply_startup, startup_enabled
from ajtwin.simulation.truth import integrate_truth, true_generation
from ajtwin.simulation.truth_alt import (
    alt_measure,
    alt_processes,
    apply_machine_atomizer,
    integrate_alt_truth,
)

# Named random streams, in a fixed order (append only: never reorder).
STREAMS = (
    "droplet_offset",
    "droplet_trend",
    "droplet_ou",
    "generation_offset",
    "generation_ou",
    "line_coefficients",
    "carrier_jitter",
    "sheath_jitter",
    "current_jitter",
    "flow_sensor",
    "current_sensor",
    "pressure_noise",
    "line_noise",
    "material_noise",
    "missing",
    "vial_weighing",
    "nozzle_residue",
    "startup",
)

# Reference operating point where the true line model equals the nominal one.
REFERENCE_INPUT = np.array([375.0, 23.0, 50.0])
REFERENCE_DROPLET_UM = 3.5
REFERENCE_VIAL_ML = 1.0


def _ou(rng: np.random.Generator, n: int, sd: float, tau_s: float, start=None) -> np.ndarray:
    """Exact 1 s discretisation of an Ornstein–Uhlenbeck process, stationary sd ``sd``."""
    if sd == 0.0 or n == 0:
        return np.zeros(n)
    a = np.exp(-1.0 / tau_s) if tau_s > 0 else 0.0
    noise = rng.standard_normal(n) * sd * np.sqrt(1.0 - a**2)
    noise[0] = sd * rng.standard_normal() if start is None else start
    return lfilter([1.0], [1.0, -a], noise)


def first_order_lag(target: np.ndarray, tau_s: float) -> np.ndarray:
    """y_{k+1} = y_k + (1 − e^{−1/τ})(target_k − y_k), starting in equilibrium y_0 = target_0."""
    if tau_s <= 0:
        return target.copy()
    b = 1.0 - np.exp(-1.0 / tau_s)
    # y_k = (1−b) y_{k−1} + b target_{k−1}; shift the input by one sample
    shifted = np.concatenate([[target[0]], target[:-1]])
    y, _ = lfilter([b], [1.0, -(1.0 - b)], shifted, zi=[(1.0 - b) * target[0]])
    return y


def true_line_coefficients(nominal: np.ndarray, factors: np.ndarray, params) -> np.ndarray:
    """The virtual printer's output coefficients (2, 8).

    Every sensitivity (columns 0–6) is the nominal one times ``factors`` (2, 7); the
    offsets γ are then set so that truth and nominal agree at the reference operating
    point (d_a 3.5 µm, φ_A in balance at 375 mA/23 sccm/1 mL, clean nozzle, Q_s 50 sccm):
    the mismatch is in how the line *responds*, not a constant bias.
    """

    truth = np.array(nominal, dtype=float).copy()
    truth[:, :7] = nominal[:, :7] * factors
    aerosol = float(steady_aerosol_fraction(REFERENCE_INPUT, REFERENCE_VIAL_ML, params))
    x_ref = np.array([REFERENCE_DROPLET_UM, REFERENCE_VIAL_ML, 0.0, 0.0, aerosol])
    nominal_y = np.asarray(output_function(x_ref, REFERENCE_INPUT, params, nominal))[:2]
    truth_y = np.asarray(output_function(x_ref, REFERENCE_INPUT, params, truth))[:2]
    truth[:, 7] += nominal_y - truth_y
    return truth


@dataclass
class Processes:
    """Exogenous per-second processes of one virtual print (display units)."""

    setpoints: np.ndarray  # (T, 3) mA, sccm, sccm
    mfc_inputs: np.ndarray  # (T, 3) true current and true MFC flows
    head_inputs: np.ndarray  # (T, 3) what reaches vial/tube/nozzle (after a leak)
    droplet_um: np.ndarray  # (T,)
    drivers: np.ndarray  # (T, 4) generation multiplier, tube/nozzle factors, evaporation mL/s
    leak_fraction: np.ndarray  # (T,)
    pressure_drift_pa: np.ndarray  # (T, 2)
    draws: dict = field(default_factory=dict)  # seeded constants, for the metadata


def make_streams(seed: int) -> dict:
    """The named random streams of one seed (fresh generators: each call starts over)."""
    return dict(
        zip(
            STREAMS,
            (
                np.random.default_rng(s)
                for s in np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
            ),
            strict=True,
        )
    )


def draw_processes(scenario: Scenario, streams: dict, setpoints=None) -> Processes:
    """Draw the exogenous processes of a scenario (layer 1).

    ``setpoints`` (T, 3) replaces the scenario's schedule (a controller's commands). No
    random draw depends on the set-points, so the same streams give the same noise
    realisation under any schedule, and every process is causal in the set-points.
    """
    cfg = scenario.config
    truth, meas, fault = cfg["truth"], cfg["measurement"], cfg["fault"]
    n = scenario.duration_s
    t = np.arange(n, dtype=float)
    if setpoints is None:
        setpoints = scenario.setpoints(n)
    else:
        setpoints = np.asarray(setpoints, dtype=float)
        if setpoints.shape != (n, 3):
            raise ValueError(f"setpoints must be ({n}, 3); got {setpoints.shape}")

    mfc_inputs = _mfc_inputs(streams, meas, setpoints)
    kind = fault["kind"]
    onset_s = scenario.fault_onset_s
    after = (t >= onset_s) if onset_s is not None else np.zeros(n, dtype=bool)
    leak = np.zeros(n)
    if kind == "carrier_leak":
        ramp_s = max(float(fault["ramp_min"]) * 60.0, 1.0)
        leak = float(fault["leak_fraction"]) * np.clip((t - onset_s) / ramp_s, 0.0, 1.0)
    head_inputs = mfc_inputs.copy()
    head_inputs[:, 1] *= 1.0 - leak
    droplet, draws = _droplet_size(streams, truth, mfc_inputs, t)
    drivers, draws["generation_offset"] = _drivers(streams, truth, fault, t, after, onset_s)
    drift = np.zeros((n, 2))
    if kind == "pressure_sensor_drift":
        hours = np.clip(t - onset_s, 0.0, None) / 3600.0
        drift[:, 0] = fault["carrier_pressure_drift_Pa_per_h"] * hours
        drift[:, 1] = fault["sheath_pressure_drift_Pa_per_h"] * hours
    processes = Processes(setpoints, mfc_inputs, head_inputs, droplet, drivers, leak, drift, draws)
    return apply_startup(processes, cfg["startup"], streams["startup"])


def _mfc_inputs(streams: dict, meas: dict, setpoints: np.ndarray) -> np.ndarray:
    """The inputs the controllers deliver (T, 3) [mA, sccm, sccm]: MFCs regulate around the
    set-point with a short correlation (AR(1)); the atomizer current wanders sample to
    sample."""
    n = len(setpoints)
    jitter = np.stack(
        [
            streams["current_jitter"].standard_normal(n) * meas["atomizer_current_jitter_mA"],
            _ou(
                streams["carrier_jitter"],
                n,
                meas["carrier_flow_jitter_sccm"],
                meas["flow_jitter_time_s"],
            ),
            _ou(
                streams["sheath_jitter"],
                n,
                meas["sheath_flow_jitter_sccm"],
                meas["flow_jitter_time_s"],
            ),
        ],
        axis=-1,
    )
    mfc_inputs = setpoints + jitter
    mfc_inputs[:, 1:] = np.maximum(mfc_inputs[:, 1:], 0.1)
    return mfc_inputs


def _droplet_size(streams: dict, truth: dict, mfc_inputs: np.ndarray, t: np.ndarray):
    """The true droplet size (T,) [µm]: a seeded start, a seeded trend that levels off, a
    slow OU wander and a lagged shift that follows carrier flow and atomizer current;
    with the draws behind it (start incl. the first shift, trend rate)."""
    n = len(t)
    droplet_start = truth["droplet_median_um"] + truth["droplet_offset_sd_um"] * float(
        streams["droplet_offset"].standard_normal()
    )
    trend_um_per_h = truth["droplet_trend_sd_um_per_h"] * float(
        streams["droplet_trend"].standard_normal()
    )
    wander = _ou(
        streams["droplet_ou"], n, truth["droplet_ou_sd_um"], truth["droplet_ou_time_s"], start=0.0
    )
    input_target = truth["droplet_carrier_um_per_sccm"] * (
        mfc_inputs[:, 1] - truth["droplet_reference_carrier_sccm"]
    ) + truth["droplet_current_um_per_mA"] * (
        mfc_inputs[:, 0] - truth["droplet_reference_current_mA"]
    )
    input_shift = first_order_lag(input_target, truth["droplet_input_lag_s"])
    # the trend starts at trend_um_per_h and levels off after ~droplet_trend_time_s
    # (a drift that kept its rate for 8 h would leave the physical range of d_a)
    trend_time_s = truth["droplet_trend_time_s"]
    if trend_time_s > 0:
        trend = trend_um_per_h / 3600.0 * trend_time_s * -np.expm1(-t / trend_time_s)
    else:
        trend = trend_um_per_h * t / 3600.0
    droplet = np.maximum(droplet_start + trend + wander + input_shift, 0.5)
    draws = {
        "droplet_start_um": droplet_start + float(input_shift[0]),
        "droplet_trend_um_per_h": trend_um_per_h,
    }
    return droplet, draws


def _drivers(streams: dict, truth: dict, fault: dict, t, after, onset_s):
    """The slow drivers (T, 4): generation efficiency (seeded offset and OU wander; an
    atomizer dropout), tube and nozzle deposition factors (a clog), evaporation [mL/s];
    with the generation offset drawn."""
    n = len(t)
    kind = fault["kind"]
    generation_offset = truth["generation_offset_sd"] * float(
        streams["generation_offset"].standard_normal()
    )
    generation_wander = _ou(
        streams["generation_ou"],
        n,
        truth["generation_ou_sd"],
        truth["generation_ou_time_s"],
        start=0.0,
    )
    generation = (1.0 + generation_offset) * np.maximum(1.0 + generation_wander, 0.0)
    if kind == "atomizer_dropout":
        duration_s = float(fault["duration_min"]) * 60.0
        active = after if duration_s <= 0 else after & (t < onset_s + duration_s)
        generation = np.where(active, generation * float(fault["generation_fraction"]), generation)
    nozzle_factor = np.full(n, float(truth["nozzle_deposition_factor"]))
    if kind == "nozzle_clog":
        clog = float(fault["nozzle_deposition_multiplier"])
        nozzle_factor = np.where(after, nozzle_factor * clog, nozzle_factor)
    evaporation = np.full(n, truth["vial_evaporation_mL_per_h"] / 3600.0)
    drivers = np.stack(
        [
            generation,
            np.full(n, float(truth["tube_deposition_factor"])),
            nozzle_factor,
            evaporation,
        ],
        axis=-1,
    )
    return drivers, generation_offset


def measure(
    scenario: Scenario, processes: Processes, outputs_true: np.ndarray, streams: dict
) -> tuple[np.ndarray, np.ndarray]:
    """The measurement layer: (measured inputs (T, 3), measured outputs (T, 5))."""
    meas = scenario.config["measurement"]
    n = len(outputs_true)
    sensor = np.stack(
        [
            streams["current_sensor"].standard_normal(n) * meas["current_sensor_noise_mA"],
            streams["flow_sensor"].standard_normal(n) * meas["flow_sensor_noise_sccm"],
            streams["flow_sensor"].standard_normal(n) * meas["flow_sensor_noise_sccm"],
        ],
        axis=-1,
    )
    # The MFC reports its own flow: a leak downstream of it is invisible here.
    inputs = processes.mfc_inputs + sensor

    y = outputs_true.copy()
    line = streams["line_noise"].standard_normal((n, 2))
    y[:, 0] *= np.exp(meas["linewidth_log_sd"] * line[:, 0])
    y[:, 1] *= np.exp(meas["overspray_log_sd"] * line[:, 1])
    # the output model's overspray dips just below 0 at the edge of the input box (I_A
    # 300 mA, Q_s 80 sccm: where a least-overspray controller sits); a camera reads 0
    y[:, 1] = np.maximum(y[:, 1], 0.0)
    y[:, 2:4] += streams["pressure_noise"].standard_normal((n, 2)) * meas["pressure_noise_Pa"]
    y[:, 2:4] += processes.pressure_drift_pa
    y[:, 4] *= np.exp(meas["material_flow_log_sd"] * streams["material_noise"].standard_normal(n))

    missing = streams["missing"].random((n, 4))
    y[missing[:, 0] < meas["line_missing_fraction"], 0:2] = np.nan
    y[missing[:, 1] < meas["pressure_missing_fraction"], 2] = np.nan
    y[missing[:, 2] < meas["pressure_missing_fraction"], 3] = np.nan
    y[missing[:, 3] < meas["material_flow_missing_fraction"], 4] = np.nan
    return inputs, y


@dataclass
class VirtualPrint:
    """Everything one virtual print produced (display units).

    ``record`` is what a user gets; the rest is the truth behind it, for tests and
    studies: ``states`` (T, 5), ``outputs_true`` (noise-free, T, 5), the processes,
    ``substrate_ink_mL`` (T,) cumulative ink onto the substrate, and the true line
    coefficients (2, 8).
    """

    record: PrintRecord
    scenario: Scenario
    processes: Processes
    states: np.ndarray
    outputs_true: np.ndarray
    substrate_ink_mL: np.ndarray
    line_coefficients: np.ndarray
    generation_ml_s: np.ndarray
    machine: MachineDeviation = field(default_factory=MachineDeviation)


def draw_line_coefficients(scenario: Scenario, streams: dict, nominal, params):
    """Seeded factors (2, 7) on the output sensitivities and the true coefficients (2, 8)."""
    factors = 1.0 + scenario.config["truth"]["line_coefficient_sd"] * streams[
        "line_coefficients"
    ].standard_normal((2, 7))
    return factors, true_line_coefficients(nominal, factors, params)


def true_initial_state(
    scenario: Scenario, processes: Processes, params, streams: dict | None = None
) -> np.ndarray:
    """True x0: the scenario's vial and deposits, φ_A in balance with the true generation.

    What the operator states is not exactly what the machine holds (``streams``: the
    "vial_weighing" and "nozzle_residue" streams of :func:`make_streams`):

    - the vial holds its stated fill plus a weighing error N(0, truth.vial_weighing_sd_mL);
    - a cleaned nozzle keeps a residue |N(0, truth.nozzle_residue_sd_um)| on top of the
      stated deposit (a deposit cannot be negative: half-normal, second moment sd²).

    base.toml weighs every fill (3 µL) and has no residue; a commissioning print (cleaned
    nozzle) sets the residue. A print that continues a machine draws neither.
    """
    cfg = scenario.config
    head0 = processes.head_inputs[0]
    vial0 = float(cfg["initial"]["vial_volume_mL"])
    nozzle0 = float(cfg["initial"]["nozzle_deposition_um"])
    weighing_sd = float(cfg["truth"].get("vial_weighing_sd_mL", 0.0))
    residue_sd = float(cfg["truth"].get("nozzle_residue_sd_um", 0.0))
    if (weighing_sd > 0.0 or residue_sd > 0.0) and streams is None:
        raise ValueError("a weighing error or a nozzle residue needs the print's random streams")
    if weighing_sd > 0.0:
        vial0 = max(vial0 + weighing_sd * float(streams["vial_weighing"].standard_normal()), 1e-6)
    if residue_sd > 0.0:
        nozzle0 += residue_sd * abs(float(streams["nozzle_residue"].standard_normal()))
    generation0 = float(true_generation(head0, vial0, processes.drivers[0, 0], params))
    aerosol0 = generation0 / float(units.sccm_to_ml_per_s(head0[1]))
    return np.array(
        [
            processes.droplet_um[0],
            vial0,
            cfg["initial"]["tube_deposition_um"],
            nozzle0,
            aerosol0,
        ]
    )


def _continuation_overrides(previous: PrintRecord, overrides: dict | None) -> dict:
    """Start where a previous virtual print of the same machine ended (vial, deposits)."""
    if not previous.has_truth:
        raise ValueError(
            "continue_from needs a record with truth columns (a virtual print); "
            f"{previous.meta.get('source_file', 'this record')} has none"
        )
    last = previous.true_states[-1]
    merged = {key: dict(value) for key, value in (overrides or {}).items()}
    initial = merged.setdefault("initial", {})
    initial.setdefault("vial_volume_mL", float(last[1]))
    initial.setdefault("tube_deposition_um", float(last[2]))
    initial.setdefault("nozzle_deposition_um", float(last[3]))
    # the vial and nozzle are the ones the previous print left: not weighed or cleaned again
    merged.setdefault("truth", {}).setdefault("vial_weighing_sd_mL", 0.0)
    merged["truth"].setdefault("nozzle_residue_sd_um", 0.0)
    scenario_table = merged.setdefault("scenario", {})
    machine = previous.meta.get("machine_id")
    if machine and machine != "unknown":
        scenario_table.setdefault("machine_id", machine)
    return merged


def generator_processes(scenario, processes, machine, seed: int, truth_generator: str):
    """The processes of the truth generator: the first's as drawn, or the second's
    (:func:`~ajtwin.simulation.truth_alt.alt_processes`), with the machine's atomizer when
    it is not the generation model (second generator only: an evaluation variant)."""
    if truth_generator not in ("model", "alt"):
        raise ValueError(f"truth generator {truth_generator!r}: choose 'model' or 'alt'")
    if truth_generator == "alt":
        processes = alt_processes(scenario, processes, seed)
    if machine.has_off_model_atomizer:
        if truth_generator != "alt":
            raise ValueError(
                f"machine {machine.name!r} has an off-model atomizer, an evaluation variant "
                "of the second truth generator: use truth_generator='alt'"
            )
        processes = apply_machine_atomizer(processes, machine, seed)
    return processes


def run_virtual_print(
    scenario: str | Path | Scenario | dict = "exp1",
    seed: int = 0,
    duration_min: float | None = None,
    overrides: dict | None = None,
    continue_from: PrintRecord | None = None,
    params=None,
    coefficients=None,
    machine=None,
    machine_seed: int | None = None,
    truth_generator: str = "model",
) -> VirtualPrint:
    """Simulate one print and keep the full truth (see :func:`simulate`)."""
    if continue_from is not None:
        overrides = _continuation_overrides(continue_from, overrides)
        # the same machine prints again unless another is named
        if machine is None and machine_seed is None and "machine" in continue_from.meta:
            machine = continue_from.meta["machine"]
    deviation = resolve_machine(machine, machine_seed)
    scenario = load_scenario(scenario, overrides)
    if duration_min is not None:
        scenario = scenario.with_duration(duration_min)
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed = {seed!r} must be a non-negative integer")
    params = load_parameters() if params is None else params
    coefficients = load_output_coefficients() if coefficients is None else coefficients
    nominal = coefficient_matrix(coefficients)
    streams = make_streams(seed)
    processes = generator_processes(
        scenario, draw_processes(scenario, streams), deviation, int(seed), truth_generator
    )
    cfg = scenario.config
    line_factors, line_coefficients = draw_line_coefficients(scenario, streams, nominal, params)
    x0 = true_initial_state(scenario, processes, params, streams)
    if truth_generator == "alt":
        truth = integrate_alt_truth(
            x0,
            processes.droplet_um,
            processes.head_inputs,
            processes.drivers,
            params,
            line_coefficients,
        )
        truth["generation_ml_s"] = np.asarray(
            true_generation(
                processes.head_inputs, truth["states"][:, 1], processes.drivers[:, 0], params
            )
        )
    else:
        truth = integrate_truth(
            x0,
            processes.droplet_um,
            processes.head_inputs,
            processes.drivers,
            params,
            line_coefficients,
            substeps=int(cfg["truth"]["integration_substeps"]),
        )
    states = truth["states"]
    if not np.isfinite(states).all():
        raise FloatingPointError(f"scenario {scenario.name!r}: the true states became non-finite")
    outputs_true = truth["outputs"]
    # this machine's plumbing, gauges, line model and camera (identity: nominal machine)
    outputs_true = deviation.apply(outputs_true, states, processes.head_inputs, params)
    if truth_generator == "alt":
        inputs, outputs = alt_measure(scenario, processes, outputs_true, int(seed))
    else:
        inputs, outputs = measure(scenario, processes, outputs_true, streams)

    n = scenario.duration_s
    columns = {TIME_COLUMN: np.arange(n, dtype=float)}
    columns.update({c: inputs[:, i] for i, c in enumerate(INPUT_COLUMNS)})
    columns.update({c: outputs[:, i] for i, c in enumerate(OUTPUT_COLUMNS)})
    columns.update({c: states[:, i] for i, c in enumerate(TRUTH_COLUMNS)})
    data = pd.DataFrame({c: columns[c] for c in (*RECORD_COLUMNS, *TRUTH_COLUMNS)})

    fault = dict(cfg["fault"])
    meta = {
        "machine_id": cfg["scenario"]["machine_id"],
        "scenario": scenario.name,
        "description": cfg["scenario"]["description"],
        "seed": int(seed),
        "platen_speed_mm_s": float(cfg["scenario"]["platen_speed_mm_s"]),
        "units": dict(UNITS),
        "fault_kind": fault["kind"],
        "fault_onset_s": scenario.fault_onset_s,
        "fault": fault,
        "duration_s": n,
        "source": f"ajtwin {__version__} virtual printer ({scenario.source})",
        "truth_draws": {
            **processes.draws,
            "line_coefficient_factors": line_factors.tolist(),
            "true_line_coefficients": line_coefficients.tolist(),
        },
        "scenario_config": cfg,
    }
    if startup_enabled(cfg["startup"]):
        # the atomizer is switched on as the log begins: the print is its run-in
        meta["atomizer_switched_on_s"] = 0.0
    if truth_generator != "model":
        meta["truth_generator"] = truth_generator
    if not deviation.is_nominal:
        meta["machine"] = deviation.as_dict()
        if meta["machine_id"] == "virtual-aj300-01":
            meta["machine_id"] = f"virtual-aj300-{deviation.name}"
    record = PrintRecord(data, meta)
    return VirtualPrint(
        record,
        scenario,
        processes,
        states,
        outputs_true,
        truth["substrate_ink_mL"],
        line_coefficients,
        truth["generation_ml_s"],
        deviation,
    )


def simulate(
    scenario: str | Path | Scenario | dict = "exp1",
    seed: int = 0,
    duration_min: float | None = None,
    overrides: dict | None = None,
    continue_from: PrintRecord | None = None,
    machine=None,
    machine_seed: int | None = None,
    truth_generator: str = "model",
) -> PrintRecord:
    """Simulate one print on the virtual printer.

    Parameters
    ----------
    scenario : str, Path, Scenario or dict
        A packaged scenario (``exp1``, ``exp2``, ``exp3``, ``nozzle_clog``,
        ``carrier_leak``, ``pressure_sensor_drift``, ``atomizer_dropout``,
        ``ink_running_low``, ``clean_long``), a scenario TOML file, or a dict of
        overrides of ``base.toml`` (docs/reference/scenarios.md).
    seed : int
        Seed of every random process; the same seed gives the same record.
    duration_min : float, optional
        Override the scenario's duration [min] (e.g. a short test).
    overrides : dict, optional
        Tables of scenario keys to change, e.g. ``{"truth": {"droplet_ou_sd_um": 0.0}}``.
    continue_from : PrintRecord, optional
        A previous virtual print of the same machine: this print starts with its final
        vial level and tube/nozzle deposits (and its machine id). The droplet size and
        the generation start afresh (a new print, a new atomizer run); seed the two
        prints differently. Explicit ``overrides["initial"]`` keys win. The machine of the
        previous print is kept unless ``machine``/``machine_seed`` name another.
    machine : str, dict or MachineDeviation, optional
        A named machine (``"paper"``, ``"nominal"``; ``data/machine_variation.toml``) or
        an explicit deviation (:mod:`ajtwin.simulation.machine`). Default: nominal machine.
    machine_seed : int, optional
        Draw the machine's deviations from this seed (independent of ``seed``).
    truth_generator : {"model", "alt"}
        ``"alt"``: the second, structurally different truth generator
        (:mod:`ajtwin.simulation.truth_alt`), for evaluation only.

    Returns
    -------
    PrintRecord
        1 Hz measured inputs and outputs (display units) plus the truth columns;
        ``meta`` holds machine id, scenario, seed, platen speed, units, fault kind
        and onset [s], the seeded truth draws and the full scenario config.

    Examples
    --------
    >>> rec = simulate("exp3", seed=1, duration_min=2.0)
    >>> len(rec), rec.meta["fault_kind"], rec.has_truth
    (120, 'none', True)
    """
    return run_virtual_print(
        scenario,
        seed,
        duration_min,
        overrides,
        continue_from,
        machine=machine,
        machine_seed=machine_seed,
        truth_generator=truth_generator,
    ).record
