"""Names of the twin's states, inputs and outputs, in the order of every array (display units).

A light module (no JAX): the registry, the commands and the pages label columns with
these names without loading the model.
"""

STATE_NAMES = (
    "droplet_diameter_um",
    "vial_volume_mL",
    "tube_deposition_um",
    "nozzle_deposition_um",
    "aerosol_fraction",
)
INPUT_NAMES = ("atomizer_current_mA", "carrier_flow_sccm", "sheath_flow_sccm")
OUTPUT_NAMES = (
    "linewidth_um",
    "overspray_um",
    "carrier_pressure_Pa",
    "sheath_pressure_Pa",
    "material_flow_mL_s",
)
STATE_SYMBOLS = ("d_a", "V_l", "ΔR_T", "ΔR_N", "φ_A")
INPUT_SYMBOLS = ("I_A", "Q_c", "Q_s")
OUTPUT_SYMBOLS = ("L_w", "L_o", "P_c", "P_s", "Q_m")
#: sizes of x, u and y
N_STATES, N_INPUTS, N_OUTPUTS = 5, 3, 5
#: the states and outputs as a person says them (pages and one-line messages)
STATE_WORDS = ("droplet size", "ink level", "tube deposit", "nozzle deposit", "aerosol density")
OUTPUT_WORDS = (
    "linewidth",
    "overspray",
    "carrier pressure",
    "sheath pressure",
    "material flow",
)
