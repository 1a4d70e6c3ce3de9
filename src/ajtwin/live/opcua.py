"""The OPC UA address space of an AJ printer (after OPC 40540 / 40001; docs/reference/opcua.md).

One namespace, ``urn:ajtwin:aerosol-jet`` (its index is looked up by URI), string node
ids that spell the browse path::

    Machines                                        (folder, as OPC 40001 places machines)
      <name>/
        Identification/  Manufacturer, Model, SerialNumber, ProductInstanceUri,
                         SoftwareRevision                                    (40001)
        Monitoring/
          Process/       AtomizerCurrent, CarrierFlow, SheathFlow, CarrierPressure,
                         SheathPressure, Linewidth, Overspray, MaterialFlow  (EngineeringUnits)
                         SampleTime [s], PrintState ("printing"/"finished"),
                         SampleBuffer (Double[n·9]: the last n samples, rows of
                         t, I_A, Q_c, Q_s, L_w, L_o, P_c, P_s, Q_m; NaN = not measured)
          SetPoints/     AtomizerCurrentSetpoint, CarrierFlowSetpoint, SheathFlowSetpoint
                         (writable by an authenticated user; EURange = the machine limits)
          Health/        <state> and <state>Std for the five twin states, NIS, TwinTime,
                         Status, Cause, Theta (Double[5]), Alarm (JSON of the last event)

The node id of a variable is ``ns=<idx>;s=<name>/Monitoring/Process/CarrierPressure``.
Alarms are ``TwinAlarmEventType`` events (Machine, Cause, OnsetTime, DetectedTime,
Detectors, AlarmState) emitted by the Server object whenever a twin writes ``Health/Alarm``.

This module holds only names, units and the functions that spell them;
:mod:`ajtwin.live.printer_server` and
:mod:`ajtwin.live.link` are the server and the client.
"""

from __future__ import annotations

from ajtwin.io.records import INPUT_COLUMNS, OUTPUT_COLUMNS
from ajtwin.model import STATE_NAMES

NAMESPACE_URI = "urn:ajtwin:aerosol-jet"
MACHINES_FOLDER = "Machines"

#: Process variables: browse name → (record column, unit display name, UNECE code)
PROCESS_VARIABLES = {
    "AtomizerCurrent": ("atomizer_current_mA", "mA", "4K"),
    "CarrierFlow": ("carrier_flow_sccm", "sccm", ""),  # standard cm³/min: no UNECE code
    "SheathFlow": ("sheath_flow_sccm", "sccm", ""),
    "Linewidth": ("linewidth_um", "µm", "4H"),
    "Overspray": ("overspray_um", "µm", "4H"),
    "CarrierPressure": ("carrier_pressure_Pa", "Pa", "PAL"),
    "SheathPressure": ("sheath_pressure_Pa", "Pa", "PAL"),
    "MaterialFlow": ("material_flow_mL_s", "mL/s", "40"),
}
SETPOINTS = {
    "AtomizerCurrentSetpoint": ("atomizer_current_mA", "mA", "4K"),
    "CarrierFlowSetpoint": ("carrier_flow_sccm", "sccm", ""),
    "SheathFlowSetpoint": ("sheath_flow_sccm", "sccm", ""),
}
#: Health variables of the twin's states: browse name → (state, unit, UNECE code)
HEALTH_STATES = {
    "DropletDiameter": ("droplet_diameter_um", "µm", "4H"),
    "VialVolume": ("vial_volume_mL", "mL", "MLT"),
    "TubeDeposition": ("tube_deposition_um", "µm", "4H"),
    "NozzleDeposition": ("nozzle_deposition_um", "µm", "4H"),
    "AerosolFraction": ("aerosol_fraction", "1", "C62"),
}
#: Columns of a SampleBuffer row
SAMPLE_COLUMNS = ("time_s", *INPUT_COLUMNS, *OUTPUT_COLUMNS)
SAMPLE_WIDTH = len(SAMPLE_COLUMNS)
IDENTIFICATION = ("Manufacturer", "Model", "SerialNumber", "ProductInstanceUri", "SoftwareRevision")
ALARM_EVENT_TYPE = "TwinAlarmEventType"

assert tuple(HEALTH_STATES[k][0] for k in HEALTH_STATES) == tuple(STATE_NAMES)


def node_path(machine: str, *parts: str) -> str:
    """String identifier of a node: ``<machine>/Monitoring/Process/CarrierPressure``."""
    return "/".join((machine, *parts))


def unece_unit_id(code: str) -> int:
    """OPC UA UnitId of a UNECE common code (the characters packed in an int; −1: none)."""
    if not code:
        return -1
    value = 0
    for char in code:
        value = (value << 8) | ord(char)
    return value


def security_string(policy: str, certificate, private_key, server_certificate=None) -> str:
    """asyncua's security string, e.g. ``Basic256Sha256,SignAndEncrypt,cert.der,key.pem``."""
    if "_" not in policy:
        raise ValueError(f"--security {policy!r}: expected e.g. Basic256Sha256_SignAndEncrypt")
    name, mode = policy.split("_", 1)
    if mode not in ("Sign", "SignAndEncrypt"):
        raise ValueError(f"--security {policy!r}: the mode must be Sign or SignAndEncrypt")
    if not certificate or not private_key:
        raise ValueError(f"--security {policy} needs --certificate and --private-key")
    parts = [name, mode, str(certificate), str(private_key)]
    if server_certificate:
        parts.append(str(server_certificate))
    return ",".join(parts)
