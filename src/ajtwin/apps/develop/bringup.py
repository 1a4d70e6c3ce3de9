"""A bring-up of a new ink: the tests printed so far, and what to print next.

A :class:`BringUp` holds the goal (a target linewidth within a tolerance, an overspray
limit), the inputs it may set (:class:`~ajtwin.apps.develop.prior.InputBox`), the machine
and the test lines printed with what they measured; it lives in a JSON file between the
operator's steps (``ajtwin develop``). :meth:`BringUp.decide` answers with one of:

``done``
    a tested recipe where P(|L_w − target| ≤ tolerance and L_o ≤ max) ≥ p (0.9) under
    the posterior (:mod:`ajtwin.apps.develop.surrogate`) — the recipe is always one that
    was printed;
``out_of_reach``
    after at least 3 tests, no input in the limits has P(feasible) above 0.02 and either the
    most promising inputs were printed or none has P above 0.002 (the posterior, its
    data-driven part included, excludes the target everywhere): the target is beyond this
    ink, with the closest it can do;
``test``
    the next test line: the inputs most likely to end the bring-up with the next reading.
    For a test at z the posterior after the reading is predicted (preposterior): its mean
    μ' ~ N(μ, σ⁴/(σ² + s²)), its σ'² = σ²s²/(σ² + s²) (s the reading's σ); the test ends the
    bring-up if |μ'_w − target| ≤ tolerance − 1.64 σ'_w and μ'_o ≤ max − 1.64 σ'_o (each at
    √p ≈ 0.95). The same for a block of n = 2 or 4 replicate lines (their mean: s/√n), per
    line: the next test maximises max_n P_n/n over a quasi-random set of the box refined around
    its best points: far from the goal it is ~0, near it but uncertain the reading's spread
    carries it, once the line is known the target's neighbourhood wins, and where one reading
    is as wide as the tolerance (a wide line) the inputs a few replicates would settle do.
    Among near-equals the one least moved by a ±5 % change of droplet size and aerosol
    density is printed.

Examples
--------
>>> from ajtwin.apps.develop.prior import InputBox
>>> b = BringUp.create(Goal(45.0, 8.0), InputBox.from_limits(None, 2.0))
>>> d = b.decide()
>>> d.kind, sorted(d.test)[:2]
('test', ['atomizer_current_mA', 'carrier_flow_sccm'])
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.special import ndtr

from ajtwin.apps.develop.prior import (
    InkPrior,
    InputBox,
    MachineLine,
    load_ink_prior,
    quasi_random,
)
from ajtwin.apps.develop.surrogate import (
    LINEWIDTH,
    MATERIAL_FLOW,
    OVERSPRAY,
    LinePosterior,
    Observations,
    Prediction,
    to_log,
)
from ajtwin.model.droplet_dynamics import load_droplet_dynamics
from ajtwin.model.names import INPUT_NAMES

FILE_FORMAT = "ajtwin-develop"
#: the names of a test's inputs (the three inputs and the platen speed)
TEST_INPUTS = (*INPUT_NAMES, "speed_mm_s")
#: the resolution the operator sets the inputs to (mA, sccm, sccm, mm/s)
RESOLUTION = np.array([1.0, 0.1, 0.1, 0.1])
#: one-sided normal quantile of √0.9 ≈ 0.949
Z_HALF = 1.6394


@dataclass(frozen=True)
class Goal:
    """What the bring-up looks for [µm]."""

    target_linewidth_um: float
    max_overspray_um: float
    tolerance_um: float = 2.0
    probability: float = 0.9

    def __post_init__(self):
        if not (np.isfinite(self.target_linewidth_um) and self.target_linewidth_um > 0):
            raise ValueError(f"target linewidth must be > 0 µm, got {self.target_linewidth_um}")
        if not (np.isfinite(self.max_overspray_um) and self.max_overspray_um > 0):
            raise ValueError(f"max overspray must be > 0 µm, got {self.max_overspray_um}")
        if not 0 < self.tolerance_um < self.target_linewidth_um:
            raise ValueError(f"tolerance must be in (0, target), got {self.tolerance_um}")
        if not 0.5 <= self.probability < 1:
            raise ValueError(f"probability must be in [0.5, 1), got {self.probability}")


@dataclass
class Decision:
    """The answer of :meth:`BringUp.decide` (module docstring)."""

    kind: str  # "test", "done" or "out_of_reach"
    message: str
    test: dict | None = None  # the next test's inputs, settle_s, print_s
    recipe: dict | None = None  # inputs and predicted L_w, L_o (mean, 2σ), probability
    closest: dict | None = None  # out of reach: the inputs closest to the goal
    window: dict | None = None  # share of the box with P ≥ p, and its input ranges
    probability: float = 0.0  # the best tested P(feasible)

    def as_dict(self) -> dict:
        """JSON-ready, with ``done`` and ``out_of_reach`` flags."""
        out = {"done": self.kind == "done", "out_of_reach": self.kind == "out_of_reach"}
        out.update({k: v for k, v in asdict(self).items() if v is not None})
        return out


def _log_goal(goal: Goal) -> tuple[float, float, float]:
    """The goal in the posterior's logarithms: (window centre, half-width, overspray limit)."""
    low, high = (
        to_log(goal.target_linewidth_um + s * goal.tolerance_um, LINEWIDTH) for s in (-1, 1)
    )
    return (
        float((low + high) / 2),
        float((high - low) / 2),
        float(to_log(goal.max_overspray_um, OVERSPRAY)),
    )


def feasibility(pred, goal: Goal) -> np.ndarray:
    """P(|L_w − target| ≤ tolerance) · P(L_o ≤ max) under the posterior (M,)."""
    centre, half, limit = _log_goal(goal)
    hi = (centre + half - pred.linewidth) / pred.linewidth_sd
    lo = (centre - half - pred.linewidth) / pred.linewidth_sd
    return (ndtr(hi) - ndtr(lo)) * ndtr((limit - pred.overspray) / pred.overspray_sd)


def finishing_probability(pred, goal: Goal, reading_sd: tuple) -> np.ndarray:
    """P(the bring-up is done after a test at each input) (M,): the preposterior rule of
    the module docstring, with readings of relative σ ``reading_sd`` = (s_w, s_o) each."""
    centre, half_width, limit = _log_goal(goal)
    prob = np.ones_like(pred.linewidth)
    for mean, sd, s, kind in (
        (pred.linewidth, pred.linewidth_sd, reading_sd[0], "window"),
        (pred.overspray, pred.overspray_sd, reading_sd[1], "limit"),
    ):
        after_sd = sd * s / np.sqrt(sd**2 + s**2)
        spread = sd**2 / np.sqrt(sd**2 + s**2)
        if kind == "window":
            half = half_width - Z_HALF * after_sd
            p = np.where(
                half > 0,
                ndtr((centre + half - mean) / spread) - ndtr((centre - half - mean) / spread),
                0.0,
            )
        else:
            p = ndtr((limit - Z_HALF * after_sd - mean) / spread)
        prob = prob * p
    return prob


def finishing_rate(pred, goal: Goal, reading_sd: tuple, replicates=(1, 2, 4)) -> np.ndarray:
    """The chance per test line that a block of n lines at each input ends the bring-up,
    max over n of P_n / n (M,): P_n is :func:`finishing_probability` with the readings'
    mean (σ/√n). Where one reading's σ is as wide as the tolerance, one line cannot end the
    bring-up but a few replicates can; the block is printed one line at a time."""
    s = np.asarray(reading_sd, dtype=float)
    return np.max(
        [finishing_probability(pred, goal, tuple(s / np.sqrt(n))) / n for n in replicates],
        axis=0,
    )


def reading_feasibility(test: dict, goal: Goal, repeatability: float) -> float:
    """P(feasible) from one test's reading alone, with no model: the reading as the line's
    value, its σ with the line's repeatability (the rule a model-free method stops by)."""
    values = {}
    for kind, key in ((LINEWIDTH, "linewidth"), (OVERSPRAY, "overspray")):
        value = test[f"{key}_um"]
        values[key] = (
            np.atleast_1d(to_log(value, kind)),
            np.atleast_1d(np.hypot(test[f"{key}_std_um"] / (value + 1.0), repeatability)),
        )
    reading = Prediction(*values["linewidth"], *values["overspray"], *([np.zeros(1)] * 4))
    return float(feasibility(reading, goal)[0])


@dataclass
class BringUp:
    """One ink's bring-up (module docstring); ``tests`` are JSON-ready dicts."""

    goal: Goal
    box: InputBox
    machine: MachineLine = field(default_factory=MachineLine)
    tests: list = field(default_factory=list)
    suggested: dict | None = None
    created: str = ""
    settings: dict = field(default_factory=load_ink_prior, repr=False)

    @classmethod
    def create(cls, goal: Goal, box: InputBox, machine: MachineLine | None = None) -> BringUp:
        """A new bring-up with no test yet."""
        now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        return cls(goal, box, machine or MachineLine(), created=now)

    # ------------------------------------------------------------------ file
    def as_dict(self) -> dict:
        """The JSON file's content."""
        return {
            "format": FILE_FORMAT,
            "format_version": 1,
            "created": self.created,
            "goal": asdict(self.goal),
            "box": self.box.as_dict(),
            "machine": self.machine.as_dict(),
            "tests": self.tests,
            "suggested": self.suggested,
        }

    @classmethod
    def from_dict(cls, values: dict, where: str = "bring-up file") -> BringUp:
        """A bring-up from :meth:`as_dict`'s content; ValueError naming ``where``."""
        if values.get("format") != FILE_FORMAT:
            raise ValueError(
                f"{where}: not an ajtwin develop file (format {values.get('format')!r})"
            )
        try:
            return cls(
                Goal(**values["goal"]),
                InputBox.from_dict(values["box"]),
                MachineLine.from_dict(values.get("machine")),
                list(values.get("tests", [])),
                values.get("suggested"),
                values.get("created", ""),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{where}: missing or wrong field {exc}") from None

    def save(self, path) -> Path:
        """Write the file atomically (a killed write leaves the previous file whole)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.as_dict(), indent=1), encoding="utf-8")
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> BringUp:
        """Read a bring-up file; ValueError naming it."""
        path = Path(path)
        try:
            values = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the bring-up file ({exc})") from None
        return cls.from_dict(values, str(path))

    # ------------------------------------------------------------------ tests
    def add_test(
        self,
        inputs,
        linewidth_um,
        overspray_um,
        *,
        linewidth_std_um=None,
        overspray_std_um=None,
        source="reading",
        extra=None,
    ) -> dict:
        """Record a test line: its inputs (4,) [mA, sccm, sccm, mm/s] and what it measured
        [µm] (σ: the operator's, or ``[test_line] reading_sd_um``)."""
        u = np.asarray(inputs, dtype=float).reshape(4)
        for value, name in ((linewidth_um, "linewidth"), (overspray_um, "overspray")):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 µm, got {value}")
        default_sd = float(self.settings["test_line"]["reading_sd_um"])
        test = {name: float(v) for name, v in zip(TEST_INPUTS, u)}
        test.update(
            linewidth_um=float(linewidth_um),
            linewidth_std_um=float(default_sd if linewidth_std_um is None else linewidth_std_um),
            overspray_um=float(overspray_um),
            overspray_std_um=float(default_sd if overspray_std_um is None else overspray_std_um),
            source=source,
            added=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        )
        if extra:
            test.update(extra)
        self.tests.append(test)
        self.suggested = None
        return test

    def observations(self) -> Observations:
        """The tests as the posterior's observations (σ with the line's repeatability)."""
        rep = float(self.settings["test_line"]["repeatability_relative"])
        kinds, inputs, values, sd = [], [], [], []
        for t in self.tests:
            u = [t[name] for name in TEST_INPUTS]
            for kind, key in ((LINEWIDTH, "linewidth"), (OVERSPRAY, "overspray")):
                kinds.append(kind)
                inputs.append(u)
                values.append(t[f"{key}_um"])
                sd.append(np.hypot(t[f"{key}_std_um"], rep * t[f"{key}_um"]))
            if t.get("material_flow_ml_s") is not None:
                kinds.append(MATERIAL_FLOW)
                inputs.append(u)
                values.append(t["material_flow_ml_s"])
                sd.append(max(t.get("material_flow_std_ml_s", 0.0), 0.15 * t["material_flow_ml_s"]))
        if not kinds:
            return Observations.empty()
        arrays = (np.array(kinds), np.array(inputs, float), np.array(values), np.array(sd))
        return Observations(*arrays)

    def posterior(self, prior: InkPrior | None = None) -> LinePosterior:
        """The ink's line given the tests."""
        prior = prior or InkPrior(self.settings, self.machine)
        return LinePosterior(prior, self.box, self.observations())

    def timing(self, speed_mm_s: float) -> tuple[int, int]:
        """(settle_s, print_s) of a test line at a speed [mm/s]."""
        cfg = self.settings["test_line"]
        response = load_droplet_dynamics("input_following").response_time_s
        settle = int(np.ceil(cfg["settle_time_constants"] * response))
        return settle, int(np.ceil(max(cfg["line_length_mm"] / speed_mm_s, 10.0)))

    def _reading_sd(self, pred_w: float, pred_o: float) -> tuple[float, float]:
        """The relative σ (log units) of a next reading of L_w and L_o near these values."""
        cfg = self.settings["test_line"]
        rep = float(cfg["repeatability_relative"])
        sd = {k: [t[f"{k}_std_um"] for t in self.tests] for k in ("linewidth", "overspray")}
        own = {k: float(np.median(v)) if v else float(cfg["reading_sd_um"]) for k, v in sd.items()}
        return (
            float(np.hypot(own["linewidth"] / (pred_w + 1.0), rep)),
            float(np.hypot(own["overspray"] / (pred_o + 1.0), rep)),
        )

    # ------------------------------------------------------------------ decisions
    def decide(self, posterior: LinePosterior | None = None) -> Decision:
        """The next step (module docstring)."""
        post = posterior or self.posterior()
        goal = self.goal
        dec = self.settings["decision"]
        candidates = self._candidates(int(dec["candidates"]))
        pred = post.predict(candidates)
        p_feasible = feasibility(pred, goal)
        window = self._window(candidates, p_feasible)
        if self.tests:
            tested = np.array([[t[n] for n in TEST_INPUTS] for t in self.tests])
            at_tests = post.predict(tested)
            p_tested = feasibility(at_tests, goal)
            best = int(np.argmax(p_tested))
            if p_tested[best] >= goal.probability:
                return self._done(tested[best], at_tests, best, p_tested[best], window)
            if self._out_of_reach(candidates, p_feasible, tested):
                return self._beyond_reach(
                    candidates, pred, p_feasible, window, float(p_tested.max())
                )
        best_p = float(p_tested.max()) if self.tests else 0.0
        return self._test(self._choose(post, candidates, pred, p_feasible), window, best_p)

    def _candidates(self, n: int) -> np.ndarray:
        return self.box.inputs(quasi_random(n, self.box.dimension, 4242))

    def _choose(self, post, candidates, pred, p_feasible) -> np.ndarray:
        """The next test's inputs: the highest finishing probability, refined locally."""
        goal = self.goal
        s = self._reading_sd(goal.target_linewidth_um, goal.max_overspray_um)
        score = finishing_rate(pred, goal, s)
        if score.max() < 1e-9:  # nothing is near: go where the goal is most plausible
            score = (
                p_feasible
                if p_feasible.max() > 1e-12
                else -np.abs(pred.linewidth - goal.target_linewidth_um) / pred.linewidth_sd
            )
        top = np.argsort(score)[-16:]
        rng = np.random.default_rng(len(self.tests))
        z_top = self.box.scaled(candidates[top])
        local = np.clip(
            np.repeat(z_top, 4, axis=0) + 0.04 * rng.standard_normal((64, z_top.shape[1])), 0, 1
        )
        pool = np.concatenate([candidates[top], self.box.inputs(local)])
        pool = self._rounded(pool)
        p = post.predict(pool)
        s_pool = finishing_rate(p, goal, s)
        if s_pool.max() < 1e-9:
            s_pool = (
                feasibility(p, goal)
                if feasibility(p, goal).max() > 1e-12
                else -np.abs(p.linewidth - goal.target_linewidth_um) / p.linewidth_sd
            )
        # among near-equals, the inputs least moved by ±5 % droplet size and aerosol density
        change = float(self.settings["decision"]["robustness_change"])
        moved = change * (np.abs(p.droplet_sensitivity) + np.abs(p.aerosol_sensitivity))
        near = s_pool >= s_pool.max() - 0.02 * abs(s_pool.max())
        return pool[np.flatnonzero(near)[np.argmin(moved[near])]]

    def _rounded(self, inputs) -> np.ndarray:
        """Inputs rounded to what an operator sets, kept within the box."""
        x = np.round(np.asarray(inputs) / RESOLUTION) * RESOLUTION
        for i, (lo, hi) in enumerate(self.box.bounds):
            x[:, i] = np.clip(x[:, i], lo, hi)
        x[:, 3] = np.clip(x[:, 3], *self.box.speed_mm_s)
        return x

    def _window(self, candidates, p_feasible) -> dict:
        """The region where P(feasible) ≥ p: its share of the box and its input ranges."""
        inside = p_feasible >= self.goal.probability
        out = {"share": float(inside.mean()), "probability": self.goal.probability}
        if inside.any():
            out["ranges"] = {
                n: [float(candidates[inside, i].min()), float(candidates[inside, i].max())]
                for i, n in enumerate(TEST_INPUTS)
            }
        return out

    def _out_of_reach(self, candidates, p_feasible, tested) -> bool:
        dec = self.settings["decision"]
        if len(self.tests) < int(dec["out_of_reach_min_tests"]):
            return False
        if p_feasible.max() >= float(dec["out_of_reach_probability"]):
            return False
        # an order below the threshold everywhere, residual included, the posterior excludes
        # the target: where its P is ~0 the "most promising" inputs are noise, not a place
        if p_feasible.max() < float(dec["out_of_reach_excluded_probability"]):
            return True
        # the most promising inputs must have been printed (not the prior's word alone)
        best = self.box.scaled(candidates[np.argmax(p_feasible)])
        distance = np.sqrt(((self.box.scaled(tested) - best) ** 2).sum(axis=1)).min()
        return bool(distance <= 0.2)

    def _test(self, inputs, window, best_p) -> Decision:
        settle, line = self.timing(float(inputs[3]))
        test = {n: round(float(v), 6) for n, v in zip(TEST_INPUTS, inputs)}
        test.update(settle_s=settle, print_s=line)
        self.suggested = test
        n = len(self.tests) + 1
        return Decision(
            "test", f"print test line {n}", test=test, window=window, probability=best_p
        )

    def _done(self, inputs, pred, index, probability, window) -> Decision:
        recipe = {n: float(v) for n, v in zip(TEST_INPUTS, inputs)}
        recipe.update(_predicted(pred, index))
        recipe.update(
            probability=float(probability),
            test=int(index) + 1,
        )
        self.suggested = None
        return Decision(
            "done",
            f"recipe found after {len(self.tests)} test lines (test {index + 1})",
            recipe=recipe,
            window=window,
            probability=float(probability),
        )

    def _beyond_reach(self, candidates, pred, p_feasible, window, best_p) -> Decision:
        goal = self.goal
        centre, _, limit = _log_goal(goal)
        ok = pred.overspray <= limit
        pool = np.flatnonzero(ok) if ok.any() else np.arange(len(candidates))
        i = pool[np.argmin(np.abs(pred.linewidth[pool] - centre))]
        closest = {n: float(v) for n, v in zip(TEST_INPUTS, candidates[i])}
        closest.update(_predicted(pred, i))
        self.suggested = None
        message = (
            f"target L_w {goal.target_linewidth_um:g} ± {goal.tolerance_um:g} µm with L_o ≤ "
            f"{goal.max_overspray_um:g} µm is out of this ink's reach within the limits "
            f"(P < {p_feasible.max():.3f} everywhere); "
            f"closest: L_w {closest['linewidth_um']:.1f} µm, "
            f"L_o {closest['overspray_um']:.1f} µm"
        )
        return Decision("out_of_reach", message, closest=closest, window=window, probability=best_p)


def _predicted(pred, index) -> dict:
    """L_w and L_o at a point with their ±2σ half-widths [µm]."""
    w, w2 = pred.in_units(LINEWIDTH, index)
    o, o2 = pred.in_units(OVERSPRAY, index)
    return {"linewidth_um": w, "linewidth_2sd_um": w2, "overspray_um": o, "overspray_2sd_um": o2}


def reading_from_record(record, settle_s: int, speed_mm_s: float) -> dict:
    """A test line's reading from its print record (camera and MFCs, 1 Hz).

    The held part is the record's last stretch whose measured inputs (a 9-s running
    median) stay within 5 mA and 0.5 sccm of their final median; its first ``settle_s``
    seconds are dropped (the line settling). Returns the inputs (4,) [mA, sccm, sccm, mm/s]
    (the held medians), the mean L_w, L_o with their standard errors, the mean Q_m and
    pressures where measured, and the number of camera frames used. ValueError when fewer
    than 5 frames remain.
    """
    u = record.inputs
    y = record.outputs
    final = np.median(u[-min(len(u), 10) :], axis=0)
    # the inputs' set-point, not their jitter: a 9-s running median of the measured inputs
    padded = np.concatenate([np.repeat(u[:1], 4, axis=0), u, np.repeat(u[-1:], 4, axis=0)])
    smooth = np.median(np.lib.stride_tricks.sliding_window_view(padded, 9, axis=0), axis=-1)
    off = (np.abs(smooth[:, 0] - final[0]) > 5.0) | (np.abs(smooth[:, 1:] - final[1:]) > 0.5).any(
        axis=1
    )
    start = int(np.flatnonzero(off)[-1]) + 1 if off.any() else 0
    if len(u) - start > settle_s + 5:
        start += int(settle_s)
    held = slice(start, len(u))
    frames = np.isfinite(y[held, 0]) & np.isfinite(y[held, 1])
    if frames.sum() < 5:
        raise ValueError(
            f"the record's held part (rows {start}-{len(u) - 1}) has {int(frames.sum())} camera "
            "readings of the line; at least 5 are needed"
        )
    w, o = y[held, 0][frames], y[held, 1][frames]
    out = {
        "inputs": np.append(np.median(u[held], axis=0), speed_mm_s),
        "linewidth_um": float(w.mean()),
        "linewidth_std_um": float(w.std(ddof=1) / np.sqrt(len(w))),
        "overspray_um": float(o.mean()),
        "overspray_std_um": float(o.std(ddof=1) / np.sqrt(len(o))),
        "frames": int(len(w)),
    }
    extra = {"frames": int(len(w)), "held_rows": [start, len(u) - 1]}
    q = y[held, 4][np.isfinite(y[held, 4])]
    if len(q) >= 5:
        extra["material_flow_ml_s"] = float(q.mean())
        extra["material_flow_std_ml_s"] = float(q.std(ddof=1) / np.sqrt(len(q)))
    pressures = y[held, 2:4]
    if np.isfinite(pressures).any():
        extra["pressures_pa"] = [float(v) for v in np.nanmean(pressures, axis=0)]
    out["extra"] = extra
    return out
