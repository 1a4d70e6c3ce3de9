"""Virtual inks: new inks for the virtual printer, whose line the twin has never seen.

An ink is drawn from an integer seed (``data/virtual_inks.toml``) by one of two generators:

``model`` (first generator)
    The packaged output model's structure with other numbers: the line's levels at the
    reference inputs, the gains on its sensitivities to φ_A, Q_c, Q_s and d_a, the
    atomizer's output (× the generation model H), the droplet size and the speed law's
    exponents. The settled line is :func:`ajtwin.model.system.output_function` with that
    coefficient matrix and speed law.
``alt`` (second generator, for evaluation only)
    Other laws: the width a power law of the focusing ratio r = Q_c/(Q_c+Q_s), of φ_A and of
    d_a, with the second truth generator's speed law (a beam footprint plus a spreading bead,
    :func:`ajtwin.simulation.truth_alt.alt_line_speed_factors`); an overspray that is a share
    of the line and rises steeply past a critical focusing ratio Q_s/Q_c; an atomizer whose
    output saturates with the current.

:class:`InkPrinter` is the stepped virtual printer (:class:`~ajtwin.simulation.stepper.
SteppedPrinter`) printing one ink: its generation is scaled by the ink's atomizer output at
the current, its droplets start at the ink's median, and :meth:`InkPrinter.print_test_line`
prints one test line (settle, then print) and returns what the camera read of it.

Examples
--------
>>> ink = draw_ink(3, "alt")
>>> ink.generator, sorted(ink.values)[:2]
('alt', ['atomizer_onset_mA', 'atomizer_output'])
>>> w, o = settled_line(ink, np.array([[375.0, 23.0, 50.0]]), 2.0)
>>> bool(abs(w[0] - ink.values["linewidth_ref_um"]) < 1e-9)   # the alt width at its reference
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.model import coefficient_matrix, load_output_coefficients, load_parameters
from ajtwin.model.line_speed import LineSpeedLaw, load_line_speed_law
from ajtwin.model.system import output_function, steady_aerosol_fraction
from ajtwin.simulation.printer import draw_processes
from ajtwin.simulation.scenarios import load_scenario
from ajtwin.simulation.stepper import SteppedPrinter
from ajtwin.simulation.truth_alt import alt_line_speed_factors, alt_processes, load_alt_settings

#: The reference inputs [mA, sccm, sccm] at which the levels are stated.
REFERENCE_INPUT = np.array([375.0, 23.0, 50.0])
GENERATORS = ("model", "alt")


def load_ink_settings() -> dict:
    """``data/virtual_inks.toml``."""
    return packaged_toml("data/virtual_inks.toml")


@dataclass(frozen=True)
class VirtualInk:
    """One drawn ink: its generator, seed and drawn values (display units)."""

    generator: str
    seed: int
    values: dict

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"generator": self.generator, "seed": self.seed, **self.values}


def _uniform(rng, bounds, log: bool = False) -> float:
    low, high = (float(b) for b in bounds)
    if log:
        return float(np.exp(rng.uniform(np.log(low), np.log(high))))
    return float(rng.uniform(low, high))


def draw_ink(seed: int, generator: str = "model", settings: dict | None = None) -> VirtualInk:
    """Draw ink ``seed`` of a generator (``"model"`` or ``"alt"``), uniformly within the
    ranges of ``data/virtual_inks.toml`` (the atomizer's output log-uniformly)."""
    if generator not in GENERATORS:
        raise ValueError(f"ink generator {generator!r}: choose 'model' or 'alt'")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"ink seed = {seed!r} must be a non-negative integer")
    cfg = (settings or load_ink_settings())[generator]
    rng = np.random.default_rng(
        np.random.SeedSequence([int(seed), 4201, GENERATORS.index(generator)])
    )
    values = {}
    for key in sorted(cfg):
        if key.endswith("_range"):
            values[key.removesuffix("_range")] = _uniform(
                rng, cfg[key], key.startswith("atomizer_output")
            )
    if generator == "alt":
        values["beam_fraction"] = _uniform(
            rng, load_alt_settings()["line_speed"]["beam_fraction_range"]
        )
    return VirtualInk(generator, int(seed), values)


def atomizer_output(ink: VirtualInk, current_ma) -> np.ndarray:
    """The ink's atomizer output relative to the generation model H at currents [mA]."""
    v = ink.values
    current = np.asarray(current_ma, dtype=float)
    if ink.generator == "model":
        return np.full_like(current, v["atomizer_output"])

    def rise(i):
        return -np.expm1(-np.maximum(i - v["atomizer_onset_mA"], 0.0) / v["atomizer_saturation_mA"])

    return v["atomizer_output"] * rise(current) / rise(REFERENCE_INPUT[0])


def droplet_response(ink: VirtualInk, inputs) -> np.ndarray:
    """The settled droplet size [µm] at inputs (..., 3): the ink's median plus the truth
    generator's steady response to Q_c and I_A (``base.toml [truth]`` / ``truth_alt.toml``)."""
    u = np.asarray(inputs, dtype=float)
    if ink.generator == "model":
        t = load_scenario("exp1").config["truth"]
        carrier, current = t["droplet_carrier_um_per_sccm"], t["droplet_current_um_per_mA"]
    else:
        d = load_alt_settings()["droplet"]
        carrier, current = d["carrier_um_per_sccm"], d["current_um_per_mA"]
    shift = carrier * (u[..., 1] - REFERENCE_INPUT[1]) + current * (u[..., 0] - REFERENCE_INPUT[0])
    return ink.values["droplet_median_um"] + shift


def _model_coefficients(ink: VirtualInk, params) -> np.ndarray:
    """The first generator's coefficient matrix (2, 8): gains on the sensitivities, offsets
    set so that the line at the reference inputs (the ink's droplets and aerosol) is the drawn
    level × the nominal machine's."""
    v = ink.values
    nominal = coefficient_matrix(load_output_coefficients())
    c = nominal.copy()
    c[:, 0] *= v["droplet_gain"]
    c[:, 1] *= v["material_gain"]
    c[:, 5:7] *= v["focusing_gain"]
    aerosol_ref = float(steady_aerosol_fraction(REFERENCE_INPUT, 1.0, params))
    x_nominal = np.array([3.5, 1.0, 0.0, 0.0, aerosol_ref])
    x_ink = np.array([v["droplet_median_um"], 1.0, 0.0, 0.0, aerosol_ref * v["atomizer_output"]])
    target = np.asarray(output_function(x_nominal, REFERENCE_INPUT, params, nominal))[:2]
    target = target * np.array([v["linewidth_level"], v["overspray_level"]])
    c[:, 7] += target - np.asarray(output_function(x_ink, REFERENCE_INPUT, params, c))[:2]
    return c


def ink_line(ink: VirtualInk, droplet_um, aerosol, inputs, speed_mm_s, params=None):
    """The ink's noise-free line (L_w, L_o) [µm] from the true droplet size, aerosol fraction
    and inputs (…, 3) at platen speed [mm/s] (a clean nozzle)."""
    params = load_parameters() if params is None else params
    d = np.asarray(droplet_um, dtype=float)
    phi = np.asarray(aerosol, dtype=float)
    u = np.broadcast_to(
        np.asarray(inputs, dtype=float), np.broadcast_shapes(d.shape, phi.shape) + (3,)
    )
    v = ink.values
    if ink.generator == "model":
        x = np.stack(
            [
                d * np.ones(u.shape[:-1]),
                np.ones(u.shape[:-1]),
                np.zeros(u.shape[:-1]),
                np.zeros(u.shape[:-1]),
                phi * np.ones(u.shape[:-1]),
            ],
            axis=-1,
        )
        law = load_line_speed_law()._replace(
            linewidth_exponent=v["linewidth_speed_exponent"],
            overspray_exponent=v["overspray_speed_exponent"],
        )
        y = np.asarray(
            output_function(x, u, params, _model_coefficients(ink, params), speed_mm_s, law)
        )
        # the linear output model runs below zero at some corners of the box for a narrow
        # ink: no line is printed there (the camera reads 0)
        return np.maximum(y[..., 0], 0.0), np.maximum(y[..., 1], 0.0)
    ratio = u[..., 1] / (u[..., 1] + u[..., 2])
    ratio_ref = REFERENCE_INPUT[1] / REFERENCE_INPUT[1:].sum()
    aerosol_ref = (
        float(steady_aerosol_fraction(REFERENCE_INPUT, 1.0, params)) * v["atomizer_output"]
    )
    width = (
        v["linewidth_ref_um"]
        * (ratio / ratio_ref) ** v["focusing_exponent"]
        * (np.maximum(phi, 1e-12) / aerosol_ref) ** v["material_exponent"]
        * (d / v["droplet_median_um"]) ** v["droplet_exponent"]
    )
    focusing = u[..., 2] / u[..., 1]
    share = (
        v["overspray_share"]
        + v["overspray_rise"] * np.maximum(focusing - v["critical_focusing_ratio"], 0.0) ** 2
    )
    law = {**_alt_speed_law(ink)}
    f_w, _ = alt_line_speed_factors(np.broadcast_to(speed_mm_s, width.shape), law)
    return width * f_w, width * share


def _alt_speed_law(ink: VirtualInk) -> dict:
    law: LineSpeedLaw = load_line_speed_law()
    return {
        "form": "beam_plus_spreading",
        "beam_fraction": ink.values["beam_fraction"],
        "spreading_exponent": float(load_alt_settings()["line_speed"]["spreading_exponent"]),
        "reference_speed_mm_s": law.reference_speed_mm_s,
        "min_speed_mm_s": law.min_speed_mm_s,
        "max_speed_mm_s": law.max_speed_mm_s,
    }


def settled_line(ink, inputs, speed_mm_s, droplet_scale=1.0, aerosol_scale=1.0, params=None):
    """The ink's settled line (L_w, L_o) [µm] at inputs (M, 3) and speeds [mm/s]: droplets at
    their settled size, φ_A in balance with the ink's generation (1 mL in the vial), a clean
    nozzle; ``droplet_scale``/``aerosol_scale`` change the droplet size and the aerosol
    density by those factors (a recipe's robustness)."""
    params = load_parameters() if params is None else params
    u = np.atleast_2d(np.asarray(inputs, dtype=float))
    aerosol = np.asarray(steady_aerosol_fraction(u, 1.0, params)) * atomizer_output(ink, u[:, 0])
    droplet = droplet_response(ink, u)
    return ink_line(ink, droplet * droplet_scale, aerosol * aerosol_scale, u, speed_mm_s, params)


@dataclass
class TestLineReading:
    """What the camera and the MFCs read of one printed test line (display units)."""

    inputs: np.ndarray  # (3,) mean measured inputs over the line
    linewidth_um: float  # mean of the camera's L_w over the line
    linewidth_std_um: float  # its standard error
    overspray_um: float
    overspray_std_um: float
    frames: int
    true_linewidth_um: float  # the true line's mean over the print (noise-free)
    true_overspray_um: float
    pressures_pa: np.ndarray  # (2,) mean P_c, P_s
    material_flow_ml_s: float


class InkPrinter(SteppedPrinter):
    """The stepped virtual printer printing one virtual ink (module docstring).

    Parameters
    ----------
    ink : VirtualInk
        Its generator is the printer's truth generator too.
    seed : int
        The print's noise (the same seed gives the same wander whatever the inputs).
    duration_min : float
        Room for every test line of the bring-up.
    """

    def __init__(self, ink: VirtualInk, seed: int, duration_min: float):
        self.ink = ink
        # the ink's draws set its level: no per-print offsets of droplet size or generation on
        # top (the wander, trend and jumps within the bring-up stay)
        overrides = {
            "truth": {
                "droplet_median_um": ink.values["droplet_median_um"],
                "droplet_offset_sd_um": 0.0,
                "generation_offset_sd": 0.0,
            }
        }
        alt = load_alt_settings()
        alt["droplet"]["offset_sd_um"] = 0.0
        alt["generation"]["offset_sd"] = 0.0
        self._alt_settings = alt
        super().__init__("exp1", seed, duration_min, overrides, truth=ink.generator)
        self._frame_rng = np.random.default_rng(np.random.SeedSequence([int(seed), 4203]))
        self._camera = (
            load_alt_settings()["measurement"]
            if ink.generator == "alt"
            else self.scenario.config["measurement"]
        )

    def _draw(self, streams, setpoints=None):
        processes = draw_processes(self.scenario, streams, setpoints=setpoints)
        if self.truth == "alt":
            processes = alt_processes(self.scenario, processes, self.seed, self._alt_settings)
        drivers = processes.drivers.copy()
        drivers[:, 0] = drivers[:, 0] * atomizer_output(self.ink, processes.mfc_inputs[:, 0])
        processes.drivers = drivers
        return processes

    def _camera_noise(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame multiplicative noise of the camera's L_w and L_o (the generator's form)."""
        c, rng = self._camera, self._frame_rng
        if self.ink.generator == "alt":
            dof = float(c["line_t_dof"])
            return 1.0 + c["linewidth_sd"] * rng.standard_t(dof, n), np.maximum(
                1.0 + c["overspray_sd"] * rng.standard_t(dof, n), 0.05
            )
        return np.exp(c["linewidth_log_sd"] * rng.standard_normal(n)), np.exp(
            c["overspray_log_sd"] * rng.standard_normal(n)
        )

    def print_test_line(
        self, inputs, speed_mm_s: float, settle_s: int, print_s: int
    ) -> TestLineReading:
        """Set the inputs, wait ``settle_s`` seconds, print ``print_s`` seconds of line at
        ``speed_mm_s`` and read it with the camera (one frame a second)."""
        self.set_setpoints(np.asarray(inputs, dtype=float))
        if settle_s > 0:
            self.advance(int(settle_s))
        chunk = self.advance(int(print_s))
        head = self.processes.head_inputs[chunk.time_s.astype(int)]
        true_w, true_o = ink_line(
            self.ink,
            chunk.true_states[:, 0],
            chunk.true_states[:, 4],
            head,
            speed_mm_s,
            self.params,
        )
        noise_w, noise_o = self._camera_noise(len(true_w))
        w, o = true_w * noise_w, np.maximum(true_o * noise_o, 0.0)
        n = len(w)
        return TestLineReading(
            inputs=chunk.inputs.mean(axis=0),
            linewidth_um=float(w.mean()),
            linewidth_std_um=float(w.std(ddof=1) / np.sqrt(n)),
            overspray_um=float(o.mean()),
            overspray_std_um=float(o.std(ddof=1) / np.sqrt(n)),
            frames=n,
            true_linewidth_um=float(true_w.mean()),
            true_overspray_um=float(true_o.mean()),
            pressures_pa=np.nanmean(chunk.outputs[:, 2:4], axis=0),
            material_flow_ml_s=float(np.nanmean(chunk.outputs[:, 4])),
        )
