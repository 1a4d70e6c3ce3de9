"""Input advice: settings that reach a target linewidth with least overspray.

The paper's "process tolerance control" with a human in the loop: from the machine's
current state estimate, find I_A, Q_c, Q_s within the machine's limits (and the validity
range of H's fit, Q_c 15–35 sccm, I_A 300–440 mA) such that the forecast linewidth after a
settling time equals the target, overspray is least (and below ``max_overspray_um`` when
given). Each candidate is scored with :func:`ajtwin.apps.planning.forecast.forecast` (the same EKF
prediction the forecast uses), so the answer carries its uncertainty.

Optimiser: SciPy SLSQP on inputs scaled to [0, 1], from several starts (the current
inputs, the box centre and corners); the best feasible result wins. If the target cannot
be reached, the settings that come closest are returned with ``reachable=False``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from ajtwin import units
from ajtwin.apps.planning.forecast import forecast
from ajtwin.model import INPUT_NAMES
from ajtwin.model.limits import DEFAULT_LIMITS

#: an advised input within this share of its search range from a bound is "on the limit"
ON_LIMIT_SHARE = 1e-3

#: validity range of H's Box–Behnken fit (model reference §4 / paper App. B.3)
H_FIT_LIMITS = {"atomizer_current_mA": (300.0, 440.0), "carrier_flow_sccm": (15.0, 35.0)}


@dataclass
class Advice:
    """Recommended inputs and what they and the current inputs will do.

    Attributes
    ----------
    inputs : array (3,)
        Recommended [I_A mA, Q_c sccm, Q_s sccm].
    predicted : dict
        Output name → (mean, σ) ``settle_s`` after the change.
    current_inputs : array (3,)
    current_predicted : dict
        The same for the inputs now.
    reachable : bool
        The target linewidth is reachable within the limits.
    target_linewidth_um, max_overspray_um : float
    bounds : list of (low, high)
        The search range per input (the machine's limits).
    settle_s : int
        When the outputs are judged [s after the change].
    message : str
        The verdict in words.
    candidates : list of dict
        Every local optimum tried.
    overspray_ok : bool
        The predicted overspray keeps the limit.
    at_limits : dict
        Input name → ``"lower"`` or ``"upper"`` for each advised input on a bound of its
        search range: the optimum may lie beyond what the machine (or H's fit) allows.
    """

    inputs: np.ndarray  # (3,) recommended [I_A mA, Q_c sccm, Q_s sccm]
    predicted: dict  # output name -> (mean, std) after the settling time
    current_inputs: np.ndarray
    current_predicted: dict
    reachable: bool
    target_linewidth_um: float
    max_overspray_um: float | None
    bounds: list
    settle_s: int
    message: str = ""
    candidates: list = field(default_factory=list)
    overspray_ok: bool = True  # predicted overspray within max_overspray_um
    at_limits: dict = field(default_factory=dict)

    def limit_note(self) -> str:
        """The advised inputs on a search limit, in words (``''`` for none)."""
        if not self.at_limits:
            return ""
        shown = ", ".join(
            f"{units.display(name).symbol} {value:g} {units.display(name).unit} ({side})"
            for name, side in self.at_limits.items()
            for value in [float(self.inputs[INPUT_NAMES.index(name)])]
        )
        return (
            f"on a search limit: {shown} — the best setting may lie beyond the range searched "
            "(the machine's limits and H's fit)"
        )

    def rows(self):
        """One row per input and output: (name, now, advised, σ of the advised output or None)."""
        names = ("linewidth_um", "overspray_um", "carrier_pressure_Pa", "sheath_pressure_Pa")
        out = []
        for i, name in enumerate(INPUT_NAMES):
            out.append((name, float(self.current_inputs[i]), float(self.inputs[i]), None))
        for name in names:
            cm, cs = self.current_predicted[name]
            m, s = self.predicted[name]
            out.append((name, cm, m, s))
        return out


def effective_bounds(limits: dict | None) -> list[tuple[float, float]]:
    """Machine limits ∩ H-fit validity, per input, as (low, high)."""

    limits = limits or DEFAULT_LIMITS
    bounds = []
    for name in INPUT_NAMES:
        low, high = limits.get(name, DEFAULT_LIMITS[name])
        if name in H_FIT_LIMITS:
            low = max(low, H_FIT_LIMITS[name][0])
            high = min(high, H_FIT_LIMITS[name][1])
        if not low < high:
            raise ValueError(f"no admissible range for {name}: [{low}, {high}]")
        bounds.append((float(low), float(high)))
    return bounds


def advise(
    twin,
    mean,
    cov,
    current_inputs,
    target_linewidth_um: float,
    *,
    max_overspray_um: float | None = None,
    limits: dict | None = None,
    settle_s: int = 120,
    tolerance_um: float = 0.05,
) -> Advice:
    """Recommend inputs (see module docstring).

    Parameters
    ----------
    twin : ajtwin.estimation.Twin (model, Σ_ξ, θ)
    mean, cov : the machine's current state estimate (display units)
    current_inputs : (3,) [mA, sccm, sccm]
    target_linewidth_um : float
    max_overspray_um : float, optional
    limits : dict, optional
        Machine limits {input name: [low, high]} (registry); default limits otherwise.
    settle_s : int
        Seconds after the change at which the outputs are judged.
    tolerance_um : float
        Accepted |L_w − target| for a solution to count as reaching the target.
    """
    if not np.isfinite(target_linewidth_um) or target_linewidth_um <= 0:
        raise ValueError(f"target linewidth must be > 0 µm, got {target_linewidth_um}")
    bounds = effective_bounds(limits)
    settled = _SettledOutputs(twin, mean, cov, bounds, settle_s)
    current = np.asarray(current_inputs, dtype=float)
    starts = [np.clip((current - settled.lo) / settled.span, 0, 1), np.full(3, 0.5)]
    starts += [
        np.array(c, dtype=float) for c in ((0.2, 0.2, 0.8), (0.8, 0.8, 0.2), (0.2, 0.8, 0.5))
    ]
    target = float(target_linewidth_um)
    on_target = {"type": "eq", "fun": lambda z: settled.outputs(z)[0] - target}
    constraints = [on_target]
    if max_overspray_um is not None:
        constraints.append(
            {"type": "ineq", "fun": lambda z: max_overspray_um - settled.outputs(z)[1]}
        )
    accept = (target, tolerance_um, max_overspray_um)
    candidates = _least_overspray(settled, starts, constraints, *accept)
    feasible = [c for c in candidates if c["hits"] and c["ok"]]
    if not feasible and max_overspray_um is not None:
        # the linewidth may be reachable, only not within the overspray limit
        candidates += _least_overspray(settled, starts, [on_target], *accept)
        feasible = [c for c in candidates if c["hits"]]
    if feasible:
        best = min(feasible, key=lambda c: c["lo"])
        reachable = True
        message = ""  # on target: said with the forecast below
        if not best["ok"]:
            message = (
                f"target linewidth reached, but the least overspray there is {best['lo']:.1f} µm "
                f"> the limit {max_overspray_um:g} µm"
            )
    else:
        best = _closest_linewidth(settled, starts, target)
        reachable = False
        message = (
            f"target {target_linewidth_um:g} µm not reachable within the limits; "
            f"closest linewidth {best['lw']:.2f} µm"
        )
    u_best = settled.inputs(best["z"])
    at_limits = {}
    for i, name in enumerate(INPUT_NAMES):
        margin = ON_LIMIT_SHARE * settled.span[i]
        if u_best[i] <= settled.lo[i] + margin:
            at_limits[name] = "lower"
        elif u_best[i] >= settled.lo[i] + settled.span[i] - margin:
            at_limits[name] = "upper"
    names = ("linewidth_um", "overspray_um", "carrier_pressure_Pa", "sheath_pressure_Pa")
    m, s = settled.predict(u_best)
    cm, cs = settled.predict(current)
    if not message:
        message = (
            f"forecast L_w {m[0]:.1f} ± {2 * s[0]:.1f} µm (2σ) {settle_s} s after the change, "
            f"on the target {target:g} µm"
        )
    return Advice(
        inputs=u_best,
        predicted={n: (float(m[i]), float(s[i])) for i, n in enumerate(names)},
        current_inputs=current,
        current_predicted={n: (float(cm[i]), float(cs[i])) for i, n in enumerate(names)},
        reachable=reachable,
        target_linewidth_um=target,
        max_overspray_um=max_overspray_um,
        bounds=bounds,
        settle_s=settle_s,
        message=message,
        candidates=[{**c, "u": settled.inputs(c["z"]).tolist()} for c in candidates],
        overspray_ok=max_overspray_um is None or float(m[1]) <= max_overspray_um + 1e-6,
        at_limits=at_limits,
    )


class _SettledOutputs:
    """The outputs ``settle_s`` seconds after setting inputs u and holding them, from the
    machine's state (the forecast), over inputs normalised to z ∈ [0, 1]³ within the bounds
    (cached: the optimiser asks for the same z many times)."""

    def __init__(self, twin, mean, cov, bounds, settle_s: int):
        self.twin, self.mean, self.cov, self.settle_s = twin, mean, cov, settle_s
        self.lo = np.array([b[0] for b in bounds])
        self.span = np.array([b[1] for b in bounds]) - self.lo
        self.cache: dict = {}

    def inputs(self, z) -> np.ndarray:
        """The inputs [mA, sccm, sccm] of a normalised z (clipped to the bounds)."""
        return self.lo + np.clip(z, 0, 1) * self.span

    def predict(self, u):
        """(means (5,), σ (5,)) of the outputs after ``settle_s`` s at inputs u."""
        fc = forecast(self.twin, self.mean, self.cov, np.tile(u, (self.settle_s, 1)))
        return fc.output_means[-1], fc.output_stds[-1]

    def outputs(self, z) -> np.ndarray:
        """The settled output means (5,) at normalised inputs z."""
        key = tuple(np.round(z, 12))
        if key not in self.cache:
            self.cache[key] = self.predict(self.inputs(z))[0]
        return self.cache[key]


def _least_overspray(settled, starts, constraints, target, tolerance_um, max_overspray_um):
    """Least overspray under ``constraints`` (SLSQP) from each start: one candidate each,
    with its linewidth, overspray, whether it hits the target and keeps the limit."""
    found = []
    for z0 in starts:
        res = optimize.minimize(
            lambda z: settled.outputs(z)[1],  # overspray, µm
            z0,
            method="SLSQP",
            bounds=[(0.0, 1.0)] * 3,
            constraints=constraints,
            options={"maxiter": 100, "ftol": 1e-6, "eps": 1e-4},
        )
        z = np.clip(res.x, 0, 1)
        y = settled.outputs(z)
        found.append(
            {
                "z": z,
                "lw": float(y[0]),
                "lo": float(y[1]),
                "hits": bool(abs(y[0] - target) <= tolerance_um),
                "ok": bool(max_overspray_um is None or y[1] <= max_overspray_um + 1e-6),
            }
        )
    return found


def _closest_linewidth(settled, starts, target) -> dict:
    """The inputs within the bounds whose settled linewidth is closest to ``target``."""
    res = min(
        (
            optimize.minimize(
                lambda z: (settled.outputs(z)[0] - target) ** 2,
                z0,
                method="L-BFGS-B",
                bounds=[(0.0, 1.0)] * 3,
                options={"eps": 1e-4},
            )
            for z0 in starts
        ),
        key=lambda r: r.fun,
    )
    y = settled.outputs(res.x)
    return {"z": np.clip(res.x, 0, 1), "lw": float(y[0]), "lo": float(y[1]), "ok": False}
