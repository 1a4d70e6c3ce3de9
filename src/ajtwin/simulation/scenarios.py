"""Virtual-printer scenarios: small TOML files merged over ``scenarios/base.toml``.

A scenario says what the operator does (input set-point steps), where the machine
starts, how the truth differs from the twin's nominal model (``[truth]``), what the
sensors add (``[measurement]``) and which fault strikes when (``[fault]``). The
packaged ones are ``exp1``, ``exp2``, ``exp3`` (model reference §10), ``nozzle_clog``,
``carrier_leak``, ``pressure_sensor_drift``, ``atomizer_dropout``,
``ink_running_low`` and ``clean_long``; a user's file of the same form works too
and needs only the keys it changes. Every key and its value: ``docs/reference/scenarios.md``.

Examples
--------
>>> s = load_scenario("exp3")
>>> s.name, s.duration_s
('exp3', 5400)
>>> s.setpoints()[2257]          # I_A mA, Q_c sccm, Q_s sccm at 37.6 min + 1 s
array([375.,  26.,  51.])
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from ajtwin.config import packaged_toml, read_toml
from ajtwin.model.names import INPUT_NAMES
from ajtwin.model.system import INPUT_LIMITS

SCENARIO_DIR = resources.files("ajtwin.simulation") / "scenarios"

#: Longest virtual print [min]: 31 days of 1 s samples (a week's soak fits, a typo's 1e9 not).
MAX_DURATION_MIN = 31 * 24 * 60.0

#: Fault kinds and the [fault] keys each one needs (besides kind and onset_min).
FAULT_FIELDS = {
    "none": (),
    "nozzle_clog": ("nozzle_deposition_multiplier",),
    "carrier_leak": ("leak_fraction", "ramp_min"),
    "pressure_sensor_drift": ("carrier_pressure_drift_Pa_per_h", "sheath_pressure_drift_Pa_per_h"),
    "atomizer_dropout": ("generation_fraction", "duration_min"),
    "ink_running_low": (),
}


def _base() -> dict:
    return packaged_toml("simulation/scenarios/base.toml")


def list_scenarios() -> list[str]:
    """Names of the packaged scenarios."""
    return sorted(
        p.name.removesuffix(".toml")
        for p in SCENARIO_DIR.iterdir()
        if p.name.endswith(".toml") and p.name != "base.toml"
    )


def _merge(base: dict, override: dict, where: str, path: str = "") -> dict:
    """Deep-merge ``override`` into a copy of ``base``; unknown keys are errors (typos)."""
    merged = copy.deepcopy(base)
    for key, value in override.items():
        here = f"{path}.{key}" if path else key
        if key == "format_version":
            continue
        if key not in base:
            # [fault] takes kind-specific keys; everything else must exist in base.toml
            if path != "fault":
                known = ", ".join(sorted(base))
                raise ValueError(f"{where}: unknown key {here!r} (known here: {known})")
            _check_type(0.0, value, where, here)  # every kind-specific fault key is a number
            merged[key] = value
            continue
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise ValueError(f"{where}: {here!r} must be a table")
            merged[key] = _merge(base[key], value, where, here)
        else:
            _check_type(base[key], value, where, here)
            merged[key] = value
    return merged


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_type(default, value, where: str, key: str) -> None:
    """A key takes the kind of value base.toml gives it: a finite number, text or a list."""
    if _is_number(default):
        if not (_is_number(value) and math.isfinite(value)):
            raise ValueError(f"{where}: {key} = {value!r} must be a finite number")
    elif isinstance(default, str) and not isinstance(value, str):
        raise ValueError(f"{where}: {key} = {value!r} must be text")
    elif isinstance(default, list) and not isinstance(value, list):
        raise ValueError(f"{where}: {key} = {value!r} must be a list of [time_min, value] pairs")


@dataclass(frozen=True)
class Scenario:
    """A merged scenario configuration (see module docstring).

    Attributes
    ----------
    name : str
        File stem (``exp1`` …).
    config : dict
        The merged tables ``scenario``, ``inputs``, ``initial``, ``truth``,
        ``measurement``, ``fault``.
    source : str
        Where it came from (packaged name or file path).
    """

    name: str
    config: dict
    source: str

    @property
    def duration_s(self) -> int:
        """Number of 1 s samples of the print."""
        return int(round(self.config["scenario"]["duration_min"] * 60.0))

    @property
    def fault_kind(self) -> str:
        """The scenario's fault (``none`` for a clean print)."""
        return self.config["fault"]["kind"]

    @property
    def fault_onset_s(self) -> float | None:
        """When the fault begins [s] (None: no fault)."""
        if self.fault_kind == "none":
            return None
        return float(self.config["fault"]["onset_min"]) * 60.0

    def setpoints(self, n_samples: int | None = None) -> np.ndarray:
        """Input set-points per second, (T, 3) [mA, sccm, sccm] (step at t ≥ step time)."""
        n = self.duration_s if n_samples is None else int(n_samples)
        t = np.arange(n, dtype=float)
        columns = []
        for name in INPUT_NAMES:
            steps = self.config["inputs"][name]
            times = np.array([s[0] for s in steps], dtype=float) * 60.0
            values = np.array([s[1] for s in steps], dtype=float)
            index = np.searchsorted(times, t + 1e-9, side="right") - 1
            columns.append(values[np.clip(index, 0, None)])
        return np.stack(columns, axis=-1)

    def with_duration(self, duration_min: float) -> Scenario:
        """The same scenario with another duration (e.g. a short test run)."""
        config = copy.deepcopy(self.config)
        config["scenario"]["duration_min"] = float(duration_min)
        _validate(config, self.source)
        return Scenario(self.name, config, self.source)


def _validate(config: dict, where: str) -> None:
    duration = config["scenario"]["duration_min"]
    if not (_is_number(duration) and math.isfinite(duration) and duration > 0):
        raise ValueError(f"{where}: scenario.duration_min = {duration!r} must be > 0")
    if not 1.0 / 60.0 <= duration <= MAX_DURATION_MIN:
        raise ValueError(
            f"{where}: scenario.duration_min = {duration!r} must be in "
            f"[1/60, {MAX_DURATION_MIN:g}] min (one 1 s sample to {MAX_DURATION_MIN / 1440:g} days)"
        )
    substeps = config["truth"]["integration_substeps"]
    if not (float(substeps).is_integer() and 1 <= substeps <= 100):
        raise ValueError(
            f"{where}: truth.integration_substeps = {substeps!r} must be an integer in [1, 100]"
        )
    for name in INPUT_NAMES:
        steps = config["inputs"][name]
        if (
            not isinstance(steps, list | tuple)
            or not steps
            or any(
                not isinstance(s, list | tuple)
                or len(s) != 2
                or not all(_is_number(v) and math.isfinite(v) for v in s)
                for s in steps
            )
        ):
            raise ValueError(
                f"{where}: inputs.{name} must be a list of [time_min, value] pairs of numbers"
            )
        times = [float(s[0]) for s in steps]
        if times[0] != 0.0:
            raise ValueError(f"{where}: inputs.{name} must start with a step at time 0")
        if any(b <= a for a, b in zip(times, times[1:], strict=False)):
            raise ValueError(f"{where}: inputs.{name} step times must increase: {times}")
        low, high = INPUT_LIMITS[name]
        for time_min, value in steps:
            if not low < float(value) <= high:
                raise ValueError(
                    f"{where}: inputs.{name} = {value!r} at {time_min} min is outside "
                    f"({low:g}, {high:g}]"
                )
    vial = config["initial"]["vial_volume_mL"]
    if not (_is_number(vial) and 0.0 < vial < 3.0):
        raise ValueError(f"{where}: initial.vial_volume_mL = {vial!r} must be in (0, 3) mL")
    for key, value in config["truth"].items():
        if not _is_number(value) or not math.isfinite(value):
            raise ValueError(f"{where}: truth.{key} = {value!r} must be a finite number")
        if (
            key.endswith("_sd")
            or "_sd_" in key
            or key.endswith("_time_s")
            or key.endswith("_factor")
        ) and value < 0:
            raise ValueError(f"{where}: truth.{key} = {value!r} must be ≥ 0")
    for key, value in config["measurement"].items():
        if not _is_number(value) or not math.isfinite(value) or value < 0:
            raise ValueError(f"{where}: measurement.{key} = {value!r} must be a number ≥ 0")
        if key.endswith("_fraction") and value >= 1:
            raise ValueError(f"{where}: measurement.{key} = {value!r} must be < 1")
    fault = config["fault"]
    kind = fault.get("kind")
    if kind not in FAULT_FIELDS:
        raise ValueError(f"{where}: fault.kind = {kind!r}; choose from {', '.join(FAULT_FIELDS)}")
    if kind != "none":
        needed = ("onset_min", *FAULT_FIELDS[kind])
        missing = [k for k in needed if k not in fault]
        if missing:
            raise ValueError(f"{where}: fault {kind!r} needs {', '.join(missing)}")
        if not 0.0 <= float(fault["onset_min"]) <= duration:
            raise ValueError(
                f"{where}: fault.onset_min = {fault['onset_min']!r} is outside the print "
                f"(0–{duration} min)"
            )
    if kind == "carrier_leak" and not 0.0 <= fault["leak_fraction"] < 1.0:
        raise ValueError(f"{where}: fault.leak_fraction must be in [0, 1)")
    if kind == "atomizer_dropout" and not 0.0 <= fault["generation_fraction"] <= 1.0:
        raise ValueError(f"{where}: fault.generation_fraction must be in [0, 1]")


def load_scenario(
    scenario: str | Path | Scenario | dict, overrides: dict | None = None
) -> Scenario:
    """A packaged scenario by name, a user's scenario file, or a dict of overrides.

    Parameters
    ----------
    scenario : str, Path, Scenario or dict
        ``"exp1"`` … (see :func:`list_scenarios`), a path to a ``.toml`` file, or a
        dict of the same tables (merged over base.toml, named ``"custom"`` unless
        ``scenario.name`` is given).
    overrides : dict, optional
        Tables of keys to change on top of the scenario, e.g.
        ``{"truth": {"nozzle_deposition_factor": 2.0}}``.

    Raises
    ------
    ValueError
        Unknown scenario, unknown key (a typo), or a value out of range.
    """
    if overrides:
        loaded = load_scenario(scenario)
        where = f"overrides of scenario {loaded.name!r}"
        config = _merge(loaded.config, overrides, where)
        _validate(config, where)
        return Scenario(loaded.name, config, loaded.source + " + overrides")
    if isinstance(scenario, Scenario):
        return scenario
    base = _base()
    if isinstance(scenario, dict):
        overrides = copy.deepcopy(scenario)
        name = str(overrides.get("scenario", {}).pop("name", "custom"))
        where = f"scenario {name!r}"
        config = _merge(base, overrides, where)
        _validate(config, where)
        return Scenario(name, config, "dict")
    text = str(scenario)
    path = Path(text)
    if text.endswith(".toml") or path.exists():
        if not path.exists():
            raise FileNotFoundError(f"scenario file not found: {path}")
        # a directory, FIFO or /dev/zero is refused before it is opened (hang, no end)
        raw = read_toml(path, what="scenario")
        name = path.stem
        source = str(path)
    else:
        packaged = SCENARIO_DIR / f"{text}.toml"
        if text == "base" or not packaged.is_file():
            raise ValueError(
                f"unknown scenario {text!r}; packaged: {', '.join(list_scenarios())} "
                "(or give a path to your own .toml file)"
            )
        raw = packaged_toml(f"simulation/scenarios/{text}.toml")
        name = text
        source = f"packaged:{text}"
    config = _merge(base, raw, source)
    _validate(config, source)
    return Scenario(name, config, source)
