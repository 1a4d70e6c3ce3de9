"""The twin's prior for an ink it has never printed: an ensemble of settled lines.

The packaged output model gives the settled line's structure (model reference §5, §12): at
held inputs u = (I_A, Q_c, Q_s) and speed ν, with φ_A in balance with the generation
(φ* = m H(u)/Q_c, :func:`ajtwin.model.system.steady_aerosol_fraction`), the droplets at
d(u) (the twin's input response, ``transition.toml``) and the machine's nozzle deposit,

    L_w(u, ν) = s_w(ν; b) [ℓ_w L_w^mach(u_ref) + G_w Δ_w(u)],
    Δ_w(u)    = g_d α^da Δd(u) + g_φ α^φ m Δφ*(u) + g_f (β^c ΔQ_c + β^s ΔQ_s),

Δ the change from the reference inputs u_ref = (375 mA, 23, 50 sccm), L^mach(u_ref) the
machine's line there (the packaged model with its calibration, gain G), s_w the speed law
(:func:`ajtwin.model.line_speed.speed_factor`), and the same form for L_o. A new ink changes
the numbers: the levels ℓ, the atomizer output m, the gains g on the sensitivities, the
droplet size and the speed exponents b, c. Drawing them from ``data/ink_prior.toml`` (a
scrambled Sobol sequence through the normal quantile: a fixed, evenly spread ensemble) and
evaluating the line for every draw at every input gives the prior as an ensemble
(:class:`LineEnsemble`); :mod:`ajtwin.apps.develop.surrogate` updates it with the tests.

Examples
--------
>>> prior = InkPrior.load()
>>> box = InputBox.from_limits(None, speed_mm_s=2.0)
>>> e = prior.ensemble(box.inputs(np.array([[0.5, 0.4, 0.4]])))
>>> e.linewidth.shape                        # (draws, points)
(256, 1)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtri

from ajtwin._aot import exported_jit
from ajtwin._jax import jnp
from ajtwin.config import packaged_toml
from ajtwin.model import coefficient_matrix, load_output_coefficients, load_parameters
from ajtwin.model.calibration import Calibration, apply_calibration
from ajtwin.model.droplet_dynamics import load_droplet_dynamics
from ajtwin.model.line_output import line_feature, material_flow
from ajtwin.model.line_speed import load_line_speed_law, speed_factor
from ajtwin.model.names import INPUT_NAMES
from ajtwin.model.system import output_function, steady_aerosol_fraction
from ajtwin.units import sccm_to_ml_per_s

#: The reference inputs [mA, sccm, sccm] at which the ink's levels are stated.
REFERENCE_INPUT = np.array([375.0, 23.0, 50.0])
#: The default input limits (the registry's defaults, within the generation fit's validity).
DEFAULT_INPUT_LIMITS = {
    "atomizer_current_mA": (300.0, 440.0),
    "carrier_flow_sccm": (15.0, 35.0),
    "sheath_flow_sccm": (30.0, 80.0),
}
#: The validity range of the generation model's fit (model reference §4).
GENERATION_FIT_LIMITS = {"atomizer_current_mA": (300.0, 440.0), "carrier_flow_sccm": (15.0, 35.0)}
#: Names of the ink's drawn values, in the order of the ensemble's columns.
INK_VALUES = (
    "linewidth_level",
    "overspray_level",
    "atomizer_output",
    "linewidth_material_gain",
    "linewidth_focusing_gain",
    "overspray_material_gain",
    "overspray_focusing_gain",
    "droplet_gain",
    "droplet_median_um",
    "linewidth_speed_exponent",
    "overspray_speed_exponent",
)


def quasi_random(n: int, dimension: int, seed: int) -> np.ndarray:
    """n points (n, dimension) in [0, 1): Roberts' R_d sequence, a low-discrepancy sequence
    from the generalised golden ratio, shifted by a seeded random offset (deterministic;
    NumPy only: ``scipy.stats.qmc`` costs a command half a second to import).

    >>> quasi_random(4, 2, 0).shape
    (4, 2)
    """
    phi = 2.0
    for _ in range(30):  # the real root of x^(d+1) = x + 1
        phi = (1.0 + phi) ** (1.0 / (dimension + 1))
    alpha = (1.0 / phi) ** np.arange(1, dimension + 1)
    shift = np.random.default_rng(seed).random(dimension)
    return (shift + np.outer(np.arange(1, n + 1), alpha)) % 1.0


def load_ink_prior() -> dict:
    """``data/ink_prior.toml``."""
    return packaged_toml("data/ink_prior.toml")


@dataclass(frozen=True)
class InputBox:
    """The inputs a bring-up may set: (low, high) per input, the speed fixed or a range.

    Points are handled scaled to [0, 1]: the three inputs linearly, the speed in ln ν.
    """

    bounds: tuple  # ((low, high) for I_A mA, Q_c sccm, Q_s sccm)
    speed_mm_s: tuple  # (low, high); low == high: a fixed speed

    @classmethod
    def from_limits(cls, limits: dict | None, speed_mm_s=2.0, speed_range=None) -> InputBox:
        """The box of a machine's limits (default limits without), within the generation
        fit's validity, at one speed or over a speed range [mm/s]."""
        limits = limits or {}
        bounds = []
        for name in INPUT_NAMES:
            low, high = (float(v) for v in limits.get(name, DEFAULT_INPUT_LIMITS[name]))
            if name in GENERATION_FIT_LIMITS:
                low = max(low, GENERATION_FIT_LIMITS[name][0])
                high = min(high, GENERATION_FIT_LIMITS[name][1])
            if not low < high:
                raise ValueError(f"no admissible range for {name}: [{low:g}, {high:g}]")
            bounds.append((low, high))
        law = load_line_speed_law()
        speeds = (float(speed_mm_s),) * 2 if speed_range is None else tuple(map(float, speed_range))
        if not law.min_speed_mm_s <= speeds[0] <= speeds[1] <= law.max_speed_mm_s:
            raise ValueError(
                f"speed {speeds[0]:g}-{speeds[1]:g} mm/s is outside the speed law's validity "
                f"{law.min_speed_mm_s:g}-{law.max_speed_mm_s:g} mm/s (line_speed.toml)"
            )
        return cls(tuple(bounds), speeds)

    @property
    def varies_speed(self) -> bool:
        """Whether the speed is an input to choose."""
        return self.speed_mm_s[1] > self.speed_mm_s[0]

    @property
    def dimension(self) -> int:
        """3, or 4 with the speed."""
        return 4 if self.varies_speed else 3

    def inputs(self, z) -> np.ndarray:
        """Points (M, dimension) in [0, 1] → inputs (M, 4): I_A mA, Q_c, Q_s sccm, ν mm/s."""
        z = np.clip(np.atleast_2d(np.asarray(z, dtype=float)), 0.0, 1.0)
        lo = np.array([b[0] for b in self.bounds])
        span = np.array([b[1] for b in self.bounds]) - lo
        u = lo + z[:, :3] * span
        if self.varies_speed:
            ln_lo, ln_hi = np.log(self.speed_mm_s)
            speed = np.exp(ln_lo + z[:, 3] * (ln_hi - ln_lo))
        else:
            speed = np.full(len(z), self.speed_mm_s[0])
        return np.column_stack([u, speed])

    def scaled(self, inputs) -> np.ndarray:
        """Inputs (M, 4) → points (M, dimension) in [0, 1] (clipped)."""
        x = np.atleast_2d(np.asarray(inputs, dtype=float))
        lo = np.array([b[0] for b in self.bounds])
        span = np.array([b[1] for b in self.bounds]) - lo
        z = (x[:, :3] - lo) / span
        if self.varies_speed:
            ln_lo, ln_hi = np.log(self.speed_mm_s)
            z = np.column_stack([z, (np.log(x[:, 3]) - ln_lo) / (ln_hi - ln_lo)])
        return np.clip(z, 0.0, 1.0)

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"bounds": [list(b) for b in self.bounds], "speed_mm_s": list(self.speed_mm_s)}

    @classmethod
    def from_dict(cls, values: dict) -> InputBox:
        """The box :meth:`as_dict` wrote."""
        return cls(
            tuple(tuple(map(float, b)) for b in values["bounds"]), tuple(values["speed_mm_s"])
        )


@dataclass(frozen=True)
class MachineLine:
    """What the prior knows of the machine: its calibration of the line and its nozzle."""

    name: str | None = None
    calibration: Calibration = field(default_factory=Calibration.identity)
    nozzle_deposition_um: float = 0.0

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {
            "name": self.name,
            "calibration": {k: float(v) for k, v in self.calibration._asdict().items()},
            "nozzle_deposition_um": float(self.nozzle_deposition_um),
        }

    @classmethod
    def from_dict(cls, values: dict | None) -> MachineLine:
        """The machine :meth:`as_dict` wrote (None: the nominal machine)."""
        if not values:
            return cls()
        return cls(
            values.get("name"),
            Calibration(**values["calibration"]),
            float(values.get("nozzle_deposition_um", 0.0)),
        )


@dataclass
class LineEnsemble:
    """The prior's settled lines at M inputs for N ink draws (display units).

    ``linewidth``, ``overspray``, ``material_flow`` are (N, M) [µm, µm, mL/s];
    ``droplet_sensitivity`` and ``aerosol_sensitivity`` (N, M) are ∂L_w/∂ln d_a and
    ∂L_w/∂ln φ_A [µm]: how much the line moves per relative change of droplet size and of
    aerosol density.
    """

    linewidth: np.ndarray
    overspray: np.ndarray
    material_flow: np.ndarray
    droplet_sensitivity: np.ndarray
    aerosol_sensitivity: np.ndarray


class InkPrior:
    """The prior over a new ink's settled line (module docstring).

    Parameters
    ----------
    settings : dict
        ``data/ink_prior.toml``.
    machine : MachineLine
        The machine the ink is brought up on (the nominal machine by default).
    """

    def __init__(self, settings: dict, machine: MachineLine | None = None):
        self.settings = settings
        self.machine = machine or MachineLine()
        self.params = load_parameters()
        self.coefficients = coefficient_matrix(load_output_coefficients())
        self.speed_law = load_line_speed_law()
        self.droplet = load_droplet_dynamics("input_following")
        self.draws = self._draw(int(settings["decision"]["ensemble_size"]))
        self.reference = self._machine_reference()

    @classmethod
    def load(cls, machine: MachineLine | None = None) -> InkPrior:
        """The packaged prior (``data/ink_prior.toml``) on a machine."""
        return cls(load_ink_prior(), machine)

    def _draw(self, n: int) -> np.ndarray:
        """(n, len(INK_VALUES)) ink draws: a scrambled Sobol sequence (fixed seed) through
        the normal quantile (log-normal factors) or uniform over a range."""
        ink, mach = self.settings["ink"], self.settings["machine"]
        known = self.machine.name is not None
        level_sd = [
            np.hypot(ink[f"{out}_level_log_sd"], 0.0 if known else mach[f"{out}_level_log_sd"])
            for out in ("linewidth", "overspray")
        ]
        u = np.clip(quasi_random(n, len(INK_VALUES), 20260), 1e-6, 1 - 1e-6)
        z = ndtri(u)
        log_sd = [
            level_sd[0],
            level_sd[1],
            ink["atomizer_output_log_sd"],
            ink["material_gain_log_sd"],
            ink["focusing_gain_log_sd"],
            ink["material_gain_log_sd"],
            ink["focusing_gain_log_sd"],
            ink["droplet_gain_log_sd"],
        ]
        draws = np.empty((n, len(INK_VALUES)))
        draws[:, :8] = np.exp(z[:, :8] * np.array(log_sd))
        draws[:, 8] = np.clip(ink["droplet_median_um"] + ink["droplet_sd_um"] * z[:, 8], 1.0, 6.0)
        for column, key in ((9, "linewidth"), (10, "overspray")):
            low, high = ink[f"{key}_speed_exponent_range"]
            draws[:, column] = low + (high - low) * u[:, column]
        return draws

    def _machine_reference(self) -> np.ndarray:
        """The machine's settled (L_w, L_o) at the reference inputs and speed, with the
        nominal droplets (3.5 µm) and generation: what the ink's levels multiply."""
        aerosol = float(steady_aerosol_fraction(REFERENCE_INPUT, 1.0, self.params))
        x = np.array([3.5, 1.0, 0.0, self.machine.nozzle_deposition_um, aerosol])
        y = output_function(x, REFERENCE_INPUT, self.params, self.coefficients)
        y = apply_calibration(y, x, REFERENCE_INPUT, self.params, self.machine.calibration)
        return np.asarray(y)[:2]

    def ensemble(self, inputs) -> LineEnsemble:
        """The prior's settled lines at inputs (M, 4) [mA, sccm, sccm, mm/s] for every draw."""
        x = np.atleast_2d(np.asarray(inputs, dtype=float))
        n = len(x)
        # a few padded sizes: each compiles once and is kept on disk (ajtwin._aot)
        size = max(ENSEMBLE_BLOCK, -(-n // ENSEMBLE_BLOCK) * ENSEMBLE_BLOCK)
        padded = np.concatenate([x, np.repeat(x[-1:], size - n, axis=0)]) if size > n else x
        cal = self.machine.calibration
        out = settled_lines(
            self.draws,
            padded,
            self.reference,
            self.coefficients,
            self.params,
            self.speed_law,
            np.array([self.droplet.carrier_um_per_sccm, self.droplet.current_um_per_mA]),
            np.array([cal.linewidth_gain, cal.overspray_gain, cal.material_flow_gain]),
        )
        return LineEnsemble(*(np.asarray(a)[:, :n] for a in out))


#: The ensemble is evaluated at a multiple of this many inputs (padded).
ENSEMBLE_BLOCK = 64


def _settled_lines(draws, inputs, reference, coefficients, params, law, droplet, gains):
    """Pure core of :meth:`InkPrior.ensemble`: (L_w, L_o, Q_m, ∂L_w/∂ln d_a, ∂L_w/∂ln φ_A),
    each (N draws, M inputs); ``droplet`` = the twin's droplet response (µm/sccm, µm/mA),
    ``gains`` = the machine's L_w, L_o and Q_m gains."""
    d = {name: draws[:, i][:, None] for i, name in enumerate(INK_VALUES)}
    u, speed = inputs[:, :3], inputs[:, 3]
    reference_input = jnp.asarray(REFERENCE_INPUT)
    aerosol = steady_aerosol_fraction(u, 1.0, params)[None, :]
    aerosol_ref = steady_aerosol_fraction(reference_input, 1.0, params)
    d_shift = (
        droplet[0] * (u[:, 1] - reference_input[1]) + droplet[1] * (u[:, 0] - reference_input[0])
    )[None, :]
    flows = [(u[:, i] - reference_input[i])[None, :] for i in (1, 2)]
    m = d["atomizer_output"]
    lines, sensitivity = [], []
    for row, out in ((0, "linewidth"), (1, "overspray")):
        gain_d = d["droplet_gain"] if row == 0 else 1.0
        c = [
            coefficients[row, 0] * gain_d,
            coefficients[row, 1] * d[f"{out}_material_gain"],
            coefficients[row, 2],
            coefficients[row, 3],
            coefficients[row, 4],
            coefficients[row, 5] * d[f"{out}_focusing_gain"],
            coefficients[row, 6] * d[f"{out}_focusing_gain"],
            0.0,  # the change from the reference: the polynomial without its offset
        ]
        change = line_feature(
            jnp.stack(jnp.broadcast_arrays(*c)), d_shift, m * (aerosol - aerosol_ref), 0.0, *flows
        )
        factor = speed_factor(speed[None, :], d[f"{out}_speed_exponent"], law)
        lines.append(factor * (d[f"{out}_level"] * reference[row] + gains[row] * change))
        if row == 0:
            sensitivity = [
                factor * gains[0] * c[0] * (d["droplet_median_um"] + d_shift),
                factor * gains[0] * c[1] * m * aerosol,
            ]
    flow = material_flow(
        m * aerosol, sccm_to_ml_per_s(u[:, 1])[None, :], params.silver_volume_fraction
    )
    # the linear output model runs below zero at some corners for a narrow ink: no line
    return jnp.maximum(lines[0], 0.0), jnp.maximum(lines[1], 0.0), flow * gains[2], *sensitivity


settled_lines = exported_jit(_settled_lines)
