"""Virtual machines that differ from the nominal model (model reference §11).

A real AJ 300 has its own plumbing, gauges, nozzle and camera. A virtual machine is
the nominal machine seen through a :class:`MachineDeviation`: carrier- and sheath-line
resistance factors, pressure-gauge gains and offsets, line-model levels and gains for
L_w and L_o, a camera scale and a Q_m gain. The sizes of the seeded draws live in
``data/machine_variation.toml`` (``[machine_variation]``), named machines such as the
paper's machine in its ``[machines.*]`` tables.

The deviation acts on the virtual printer's noise-free outputs (before sensor noise):

    L_w = s_cam (g_w L_w^true + o_w),  L_o = s_cam (g_o L_o^true + o_o),
    P_c = G_c [P_c^true + (k_c − 1) Q_c R_line,c] + O_c,  P_s likewise with k_s,
    Q_m = g_m Q_m^true,

which is the form of the twin's :class:`~ajtwin.model.calibration.Calibration` with
gain s_cam·g and offset s_cam·o (:meth:`MachineDeviation.calibration`): the calibration
that commissioning should recover.

Examples
--------
>>> m = draw_machine(3)
>>> 0.85 <= m.carrier_line_factor <= 1.15
True
>>> nominal_machine().is_nominal
True
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.model import DigitalModel
from ajtwin.model.calibration import Calibration, apply_calibration

#: Reference operating point of the line levels [mA, sccm, sccm], d_a [µm], V_l [mL].
REFERENCE_INPUT = np.array([375.0, 23.0, 50.0])
REFERENCE_DROPLET_UM = 3.5
REFERENCE_VIAL_ML = 1.0


def load_machine_variation() -> dict:
    """The packaged ``data/machine_variation.toml`` as a dict."""
    return packaged_toml("data/machine_variation.toml")


@dataclass(frozen=True)
class MachineDeviation:
    """How one virtual machine differs from the nominal model (display units)."""

    name: str = "nominal"
    carrier_line_factor: float = 1.0
    sheath_line_factor: float = 1.0
    carrier_gauge_gain: float = 1.0
    sheath_gauge_gain: float = 1.0
    carrier_gauge_offset_Pa: float = 0.0
    sheath_gauge_offset_Pa: float = 0.0
    linewidth_gain: float = 1.0
    linewidth_offset_um: float = 0.0
    overspray_gain: float = 1.0
    overspray_offset_um: float = 0.0
    camera_scale: float = 1.0
    material_flow_gain: float = 1.0
    #: the atomizer's output relative to the generation model H (a state-side deviation the
    #: output calibration does not hold; commissioning sees only its product with the Q_m
    #: gain). Drawn only by the second generator's off-model atomizer variant
    #: (:func:`ajtwin.simulation.truth_alt.off_model_atomizer_machine`), evaluation only.
    atomizer_output: float = 1.0
    #: half-range of the per-print linear trend of the atomizer's efficiency [1/h]
    atomizer_wander_per_h: float = 0.0

    @property
    def is_nominal(self) -> bool:
        """Whether this machine is the nominal model (no deviation)."""
        return self.calibration().is_identity() and not self.has_off_model_atomizer

    @property
    def has_off_model_atomizer(self) -> bool:
        """Whether the atomizer departs from the generation model (output or wander)."""
        return self.atomizer_output != 1.0 or self.atomizer_wander_per_h != 0.0

    def calibration(self) -> Calibration:
        """The equivalent twin calibration (camera scale folded into the line gains)."""
        s = self.camera_scale
        return Calibration(
            linewidth_gain=s * self.linewidth_gain,
            linewidth_offset_um=s * self.linewidth_offset_um,
            overspray_gain=s * self.overspray_gain,
            overspray_offset_um=s * self.overspray_offset_um,
            carrier_line_factor=self.carrier_line_factor,
            carrier_gauge_gain=self.carrier_gauge_gain,
            carrier_gauge_offset_Pa=self.carrier_gauge_offset_Pa,
            sheath_line_factor=self.sheath_line_factor,
            sheath_gauge_gain=self.sheath_gauge_gain,
            sheath_gauge_offset_Pa=self.sheath_gauge_offset_Pa,
            material_flow_gain=self.material_flow_gain,
        )

    def as_dict(self) -> dict:
        """The deviations and the calibration they amount to, as plain values."""
        out = asdict(self)
        out["equivalent_calibration"] = {
            k: float(v) for k, v in self.calibration()._asdict().items()
        }
        return out

    @classmethod
    def from_dict(cls, values: dict) -> MachineDeviation:
        """A deviation saved by :meth:`as_dict`."""
        fields = {k: v for k, v in values.items() if k != "equivalent_calibration"}
        return cls(**fields)

    def apply(self, outputs, states, inputs, params) -> np.ndarray:
        """Outputs (T, 5) of this machine from the nominal machine's (T, 5)."""
        if self.calibration().is_identity():
            return np.asarray(outputs, dtype=float)
        return np.asarray(apply_calibration(outputs, states, inputs, params, self.calibration()))


def nominal_machine() -> MachineDeviation:
    """The machine the nominal model describes (no deviation)."""
    return MachineDeviation()


def _reference_lines() -> np.ndarray:
    """Nominal (L_w, L_o) [µm] at the reference point."""

    model = DigitalModel.default()
    aerosol = float(model.steady_aerosol_fraction(REFERENCE_INPUT, REFERENCE_VIAL_ML))
    x = np.array([REFERENCE_DROPLET_UM, REFERENCE_VIAL_ML, 0.0, 0.0, aerosol])
    return np.asarray(model.outputs(x, REFERENCE_INPUT))[:2]


def draw_machine(seed: int, variation: dict | None = None) -> MachineDeviation:
    """A virtual machine drawn from ``seed`` (uniform deviations, sizes from the data file)."""
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"machine seed = {seed!r} must be a non-negative integer")
    sizes = (variation or load_machine_variation())["machine_variation"]
    # its own stream: the print's seed and the machine's seed are independent
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 12]))

    def rel(key):
        return 1.0 + sizes[key] * rng.uniform(-1.0, 1.0)

    def absolute(key):
        return sizes[key] * rng.uniform(-1.0, 1.0)

    carrier_line, sheath_line = rel("carrier_line_factor"), rel("sheath_line_factor")
    carrier_gain, sheath_gain = rel("carrier_gauge_gain"), rel("sheath_gauge_gain")
    carrier_offset = absolute("carrier_gauge_offset_Pa")
    sheath_offset = absolute("sheath_gauge_offset_Pa")
    lw_level, lw_gain = rel("linewidth_level"), rel("linewidth_gain")
    lo_level, lo_gain = rel("overspray_level"), rel("overspray_gain")
    camera, material = rel("camera_scale"), rel("material_flow_gain")
    ref_lw, ref_lo = _reference_lines()
    return MachineDeviation(
        name=f"seed-{int(seed)}",
        carrier_line_factor=carrier_line,
        sheath_line_factor=sheath_line,
        carrier_gauge_gain=carrier_gain,
        sheath_gauge_gain=sheath_gain,
        carrier_gauge_offset_Pa=carrier_offset,
        sheath_gauge_offset_Pa=sheath_offset,
        linewidth_gain=lw_gain,
        linewidth_offset_um=(lw_level - lw_gain) * ref_lw,
        overspray_gain=lo_gain,
        overspray_offset_um=(lo_level - lo_gain) * ref_lo,
        camera_scale=camera,
        material_flow_gain=material,
    )


def named_machine(name: str, variation: dict | None = None) -> MachineDeviation:
    """A named machine of the data file (e.g. ``"paper"``)."""
    if name == "nominal":
        return nominal_machine()
    machines = (variation or load_machine_variation()).get("machines", {})
    if name not in machines:
        known = ", ".join(["nominal", *sorted(machines)])
        raise ValueError(f"unknown named machine {name!r} (known: {known})")
    p = dict(machines[name])
    ref_lw, ref_lo = _reference_lines()
    lw_gain = float(p.pop("linewidth_gain", 1.0))
    lo_gain = float(p.pop("overspray_gain", 1.0))
    fields = {
        "linewidth_gain": lw_gain,
        "overspray_gain": lo_gain,
        "linewidth_offset_um": float(p.pop("linewidth_level_um", ref_lw)) - lw_gain * ref_lw,
        "overspray_offset_um": float(p.pop("overspray_level_um", ref_lo)) - lo_gain * ref_lo,
    }
    p.pop("description", None)
    fields.update({k: float(v) for k, v in p.items()})
    return MachineDeviation(name=name, **fields)


def resolve_machine(machine=None, machine_seed: int | None = None) -> MachineDeviation:
    """A MachineDeviation from a machine name / deviation / dict and/or a seed."""
    if machine is not None and machine_seed is not None:
        raise ValueError("give a named machine or a machine seed, not both")
    if machine_seed is not None:
        return draw_machine(machine_seed)
    if machine is None:
        return nominal_machine()
    if isinstance(machine, MachineDeviation):
        return machine
    if isinstance(machine, dict):
        return MachineDeviation.from_dict(machine)
    return named_machine(str(machine))
