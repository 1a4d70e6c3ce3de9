"""The physics macro-model of the AJ printer (paper §6, model reference §3–6).

Sub-models, each a named pure JAX function:

=====================================  ==============================================
paper name                             function
=====================================  ==============================================
log-normal droplet distribution p(d)   :func:`droplets.lognormal_quadrature`
Cunningham slip correction             :func:`droplets.cunningham_slip_correction`
settling velocity v_ts                 :func:`droplets.settling_velocity`
Stokes–Einstein diffusion D            :func:`droplets.diffusion_coefficient`
gravitational settling P_grav          :func:`transport.settling_survival`
diffusion survival P_diff              :func:`transport.diffusion_survival`
tube deposition dΔR_T/dt               :func:`transport.tube_deposition_rate`
nozzle deposition dΔR_N/dt             :func:`transport.nozzle_deposition_rate`
net droplet generation H               :func:`atomizer.net_droplet_generation`
aerosol volume fraction dφ_A/dt        :func:`atomizer.aerosol_fraction_rate`
ink volume dV_l/dt                     :func:`atomizer.vial_volume_rate`
tube resistance R_T                    :func:`fluidics.tube_resistance`
nozzle-tip resistance R_3^N            :func:`fluidics.nozzle_tip_resistance`
carrier / sheath pressure P_c, P_s     :func:`fluidics.carrier_pressure`, ``sheath_pressure``
linewidth / overspray L_w, L_o         :func:`line_output.linewidth`, :func:`line_output.overspray`
material flow Q_m                      :func:`line_output.material_flow`
line vs platen speed ν (§12)           :func:`line_speed.apply_line_speed`
transition f, output g                 :func:`system.transition_rates`, ``output_function``
=====================================  ==============================================

The names of states, inputs and outputs (:mod:`~ajtwin.model.names`) and the parameter
files (:mod:`~ajtwin.model.parameters`) load without JAX; the model's functions
(:mod:`~ajtwin.model.system`) are imported on first use, so code that only names the
states (the registry, the commands) stays light.
"""

import importlib

from ajtwin.model.names import (
    INPUT_NAMES,
    N_INPUTS,
    N_OUTPUTS,
    N_STATES,
    OUTPUT_NAMES,
    STATE_NAMES,
)
from ajtwin.model.parameters import (
    OutputCoefficients,
    PhysicalParameters,
    load_noise,
    load_output_coefficients,
    load_parameters,
)

#: the model's functions, from :mod:`ajtwin.model.system` on first use (it loads JAX)
_SYSTEM = (
    "DigitalModel",
    "coefficient_matrix",
    "euler_step",
    "ink_flows",
    "output_function",
    "rk4_step",
    "simulate_open_loop",
    "steady_aerosol_fraction",
    "transition_rates",
)
#: the line's speed law, from :mod:`ajtwin.model.line_speed` on first use (it loads JAX)
_LINE_SPEED = ("LineSpeedLaw", "apply_line_speed", "load_line_speed_law")


def __getattr__(name):
    if name in _SYSTEM:
        return getattr(importlib.import_module("ajtwin.model.system"), name)
    if name in _LINE_SPEED:
        return getattr(importlib.import_module("ajtwin.model.line_speed"), name)
    raise AttributeError(f"module 'ajtwin.model' has no attribute {name!r}")


__all__ = [
    "DigitalModel",
    "PhysicalParameters",
    "OutputCoefficients",
    "load_parameters",
    "load_output_coefficients",
    "load_noise",
    "transition_rates",
    "output_function",
    "euler_step",
    "rk4_step",
    "simulate_open_loop",
    "steady_aerosol_fraction",
    "ink_flows",
    "coefficient_matrix",
    "LineSpeedLaw",
    "load_line_speed_law",
    "apply_line_speed",
    "STATE_NAMES",
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "N_STATES",
    "N_INPUTS",
    "N_OUTPUTS",
]
