"""Columns that look like data and are not: constant, or printed too coarsely.

A spreadsheet export with 3 decimals makes ``material_flow_mL_s`` (~1.5e-8 mL/s) a column
of zeros; whole 10 µm make the linewidth a staircase. Such a column passes every range
check, and the twin would take it for measurements. :class:`ColumnQuality` gathers, chunk
by chunk, what tells: how many values, how many repeat, the smallest step between distinct
values (the column's resolution q), the typical magnitude. :func:`judge` then compares q
with the noise σ the twin assumes for that output (``ajtwin/data/noise.toml``) and with
the input limits of ``ajtwin/io/resolution.toml`` (the file explains the numbers):

* an output whose values are all the same (≥ ``min_values`` of them) — a dead sensor or a
  resolution far beyond its noise — or whose resolution exceeds
  ``max_quantum_per_sigma`` σ while most values repeat, is **treated as missing** (the
  pressures, which alone see the nozzle: the file is refused; ``refuse_when_unusable``);
* an input with a resolution beyond its ``max_quantum`` is **refused** (inputs are never
  missing). A constant input is fine: set-points are held.

Examples
--------
>>> q = ColumnQuality()
>>> q.add(np.round(43 + np.random.default_rng(0).normal(0, 2, 600), -1))  # 10 µm steps
>>> verdict = judge({"linewidth_um": q}, "log.csv")
>>> verdict.missing["linewidth_um"][:60]
'values step by 10 µm (resolution), but the twin expects this'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from ajtwin.config import packaged_toml
from ajtwin.io.schema import UNITS as COLUMN_UNITS

#: Output columns judged against their measurement noise (names as in noise.toml).
OUTPUT_NOISE_KEYS = {
    "linewidth_um": "linewidth_um",
    "overspray_um": "overspray_um",
    "carrier_pressure_Pa": "carrier_pressure_Pa",
    "sheath_pressure_Pa": "sheath_pressure_Pa",
    "material_flow_mL_s": "material_flow_relative",
}
_SHOWN_UNITS = {"um": "µm"}


@lru_cache(maxsize=1)
def settings() -> dict:
    """``resolution.toml`` with the output σ's from ``noise.toml`` (the tuning it names)."""
    table = packaged_toml("io/resolution.toml")
    noise = packaged_toml("data/noise.toml")
    tuning = table["outputs"]["noise_tuning"]
    measurement = (noise[tuning] if tuning != "paper" else noise)["measurement"]
    table["outputs"]["sigma"] = {
        column: float(measurement[key]["value"]) for column, key in OUTPUT_NOISE_KEYS.items()
    }
    return table


@dataclass
class ColumnQuality:
    """What one column's values tell about its resolution, gathered chunk by chunk."""

    n: int = 0
    repeated: int = 0
    low: float = np.inf
    high: float = -np.inf
    quantum: float = np.inf  # smallest positive step between distinct values seen
    abs_sum: float = 0.0

    def add(self, values) -> None:
        """Take one chunk of a column's values into the running figures (NaN skipped)."""
        values = np.asarray(values, dtype=float)
        finite = values[np.isfinite(values)]
        if not finite.size:
            return
        distinct = np.unique(finite)
        self.n += finite.size
        self.repeated += finite.size - distinct.size
        self.low = min(self.low, float(distinct[0]))
        self.high = max(self.high, float(distinct[-1]))
        if distinct.size > 1:
            self.quantum = min(self.quantum, float(np.min(np.diff(distinct))))
        self.abs_sum += float(np.abs(finite).sum())

    @property
    def constant(self) -> bool:
        """Whether every finite value seen so far is the same."""
        return self.n > 0 and self.low == self.high

    @property
    def typical(self) -> float:
        """Mean absolute value of the finite values (NaN before any)."""
        return self.abs_sum / self.n if self.n else np.nan


@dataclass
class Verdict:
    """Output columns to treat as missing (column → reason) and input refusals (reasons)."""

    missing: dict[str, str] = field(default_factory=dict)
    refused: list[str] = field(default_factory=list)


def _unit(column: str) -> str:
    unit = COLUMN_UNITS[column]
    return _SHOWN_UNITS.get(unit, unit)


def judge(quality: dict[str, ColumnQuality], where: str) -> Verdict:
    """Which columns are unusable, and why (see the module doc)."""
    table = settings()
    out = table["outputs"]
    verdict = Verdict()
    for column, q in quality.items():
        if q.n < out["min_values"]:
            continue
        unit = _unit(column)
        coarse_enough = q.repeated >= out["min_repeated_share"] * q.n
        if column in out["sigma"]:
            sigma = out["sigma"][column]
            if column == "material_flow_mL_s":
                sigma *= q.typical  # noise.toml gives it relative to the flow
            allowed = out["max_quantum_per_sigma"] * sigma
            if q.constant:
                verdict.missing[column] = (
                    f"all {q.n} values are {q.low:g} {unit}: a sensor that scatters by "
                    f"σ ≈ {out['sigma'][column]:g}"
                    + (" of its value" if column == "material_flow_mL_s" else f" {unit}")
                    + " never repeats one value — a dead sensor, or an export with too few "
                    "decimals"
                )
            elif coarse_enough and np.isfinite(allowed) and q.quantum > allowed:
                verdict.missing[column] = (
                    f"values step by {q.quantum:.3g} {unit} (resolution), but the twin expects "
                    f"this sensor to scatter by σ ≈ {sigma:.3g} {unit}; a resolution coarser "
                    f"than {out['max_quantum_per_sigma']:g} σ = {allowed:.3g} {unit} hides what "
                    "it measures — export with more decimals"
                )
        elif column in table.get("inputs", {}):
            limit = table["inputs"][column]
            # a constant input is a held set-point, not a coarse export
            if coarse_enough and np.isfinite(q.quantum) and q.quantum > limit["max_quantum"]:
                verdict.refused.append(
                    f"{where}: column {column!r}: values step by {q.quantum:.3g} {unit} "
                    f"(resolution); the twin needs at most {limit['max_quantum']:g} {unit} — "
                    f"{limit['why']}. Export the column with more decimals"
                )
    return verdict
