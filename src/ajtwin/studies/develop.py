"""How many test lines a new ink takes: the twin against a generic Bayesian optimisation and a
grid design of experiments, on virtual inks of both generators.

Each virtual ink (:mod:`ajtwin.simulation.virtual_ink`) is printed by the stepped virtual
printer; a bring-up prints test lines (settle, then print, read by the camera) until its
method stops or 20 tests are spent. Per ink the goal is a target L_w (a quantile of the ink's
settled L_w over the limits among inputs that keep the overspray limit, itself a quantile of
its L_o: ``data/virtual_inks.toml [targets]``), ±2 µm, or, for the out-of-reach inks, a
target 12 µm beyond the widest (or the narrowest) line the ink can print within the limit.

Methods, on the same inputs, limits (the default limits, 2 mm/s) and printer noise:

``twin``
    :class:`ajtwin.apps.develop.BringUp`: the physics ensemble and residual, the
    preposterior choice, done when its posterior gives P ≥ 0.9 at a printed recipe.
``bo``
    scikit-optimize's GP minimiser (Matérn kernel, expected improvement, 5 initial points)
    of ((L_w − target)/2 µm)² + 25 max(0, L_o/max − 1)² on the readings; done when a reading
    alone gives P ≥ 0.9 (the same probability, without a model: the reading's own σ with the
    line's repeatability).
``grid``
    a Box–Behnken design of the three inputs (13 runs), then a quadratic response surface of
    ln L_w and ln L_o printed at its best inputs and refitted after each confirmation run;
    done by the same reading rule.

The baselines are also judged by the lenient rule a lab uses without a model — stop at the
first reading within ± 2 µm of the target with L_o ≤ max ("(reading in tolerance)"): it is read
off the same run (the path up to it is the method's), stops earlier and can miss silently.

A method is *done* at the test where it stops with a recipe. The recipe *holds* when **the
line the lab prints next** is within ±2 µm of the target with L_o ≤ max: after the stop, the
same virtual printer (the same seed, continuing in time) prints one more test line at the
recipe's inputs, with the same settle and print times, and its noise-free line (the mean true
L_w and L_o over the print, ``true_linewidth_um``/``true_overspray_um``) decides. That is
what a lab prints after a bring-up, on the machine as it then stands: the droplet size and the
atomizer wander, trend and jump during a bring-up, and that is the machine's, not the ink's.
The next print is evaluation only: it is never added to the bring-up's tests and never seen by
the method.

Every method and variant is judged by this one rule, each at *its own* stop. The next print is
printed on a replay (:meth:`VirtualLab.next_print`): a new printer of the same seed prints the
first k test lines of the run at their inputs (same settle and print) and then the recipe. The
printer's noise is a function of its seed and of time, drawn from fresh copies of the seeded
streams whatever the set-points, and its states follow the commands so far, so the replay is
the run up to its k-th test exactly (checked against the run's stored readings, camera noise
included, before the recipe is printed) and its next line is the one the lab would have
printed had it stopped there. This matters for the lenient variants: their stop is read off
the same run at an earlier test k, after which the run went on printing other inputs; continuing
the run's printer would judge them minutes later, on a machine state they never stopped at. For
the methods themselves k is the run's last test, and the replay's next line is the one the
run's own printer prints next (``tests/test_develop.py`` pins the two equal).

Reported with it, by the same counts: whether the recipe holds *at the nominal machine
state* — the ink's settled line (:func:`~ajtwin.simulation.virtual_ink.settled_line`) at the
machine's nominal droplet size and aerosol density, which no lab prints but which says whether
the recipe is right for the ink rather than for the machine's state then — and the recipe's
robustness (the settled L_w after ±5 % droplet size and aerosol density). Tests until a recipe
that holds (median, 90th percentile; a recipe that does not hold, or none in 20, counts as 21),
the share done within 12 and the silent misses (a recipe that does not hold) are given by the
next print and, separately, at the nominal state; on the out-of-reach inks, whether the method
said so.

Run: ``python -m ajtwin.studies.develop [--inks N] [--first SEED] [--methods twin,bo,grid]``
(needs the ``study`` extra for ``bo``: ``pip install -e '.[study]'``); writes
``docs/results/develop/results.json`` and ``.md``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import qmc

from ajtwin.apps.develop.bringup import TEST_INPUTS, BringUp, Goal, reading_feasibility
from ajtwin.apps.develop.prior import InputBox
from ajtwin.simulation.virtual_ink import (
    InkPrinter,
    TestLineReading,
    draw_ink,
    load_ink_settings,
    settled_line,
)

OUT = Path(__file__).resolve().parents[3] / "docs" / "results" / "develop"
MAX_TESTS = 20
#: one virtual test line: settle and print as the twin asks for every method
SPEED_MM_S = 2.0


def goal_for(ink, out_of_reach: bool = False, settings: dict | None = None) -> Goal:
    """The goal the study sets an ink (module docstring)."""
    cfg = (settings or load_ink_settings())["targets"]
    box = InputBox.from_limits(None, SPEED_MM_S)
    u = box.inputs(qmc.Sobol(3, scramble=True, seed=11).random(4096))
    w, o = settled_line(ink, u[:, :3], SPEED_MM_S)
    limit = float(np.quantile(o, cfg["overspray_quantile"]))
    keep = o <= 0.9 * limit
    rng = np.random.default_rng(np.random.SeedSequence([ink.seed, 4207]))
    if out_of_reach:
        above = rng.random() < 0.5 or w[keep].min() < 20.0
        margin = float(cfg["out_of_reach_margin_um"])
        target = w[o <= limit].max() + margin if above else w[o <= limit].min() - margin
    else:
        target = float(np.quantile(w[keep], rng.uniform(*cfg["linewidth_quantile_range"])))
    return Goal(round(float(target), 1), round(limit, 1))


class VirtualLab:
    """One ink on the virtual printer: prints test lines, keeps them."""

    def __init__(self, ink, seed: int, bringup: BringUp):
        self.ink, self.bringup, self.seed = ink, bringup, int(seed)
        settle, line = bringup.timing(SPEED_MM_S)
        self.settle_s, self.print_s = settle, line
        self.printer = self._new_printer()

    def _new_printer(self) -> InkPrinter:
        # room for every test of the budget and the next print after it
        return InkPrinter(
            self.ink, self.seed, (MAX_TESTS + 2) * (self.settle_s + self.print_s) / 60.0
        )

    def _print_line(self, printer: InkPrinter, inputs) -> TestLineReading:
        return printer.print_test_line(
            np.asarray(inputs, dtype=float)[:3], SPEED_MM_S, self.settle_s, self.print_s
        )

    def print(self, inputs) -> dict:
        """Print a test line at inputs (3,) or (4,) and add its reading to the bring-up."""
        u = np.append(np.asarray(inputs, dtype=float)[:3], SPEED_MM_S)
        r = self._print_line(self.printer, u)
        return self.bringup.add_test(
            u,
            r.linewidth_um,
            r.overspray_um,
            linewidth_std_um=r.linewidth_std_um,
            overspray_std_um=r.overspray_std_um,
            source="virtual camera",
            extra={
                "true_linewidth_um": r.true_linewidth_um,
                "true_overspray_um": r.true_overspray_um,
            },
        )

    def next_print(self, recipe, stop: int) -> TestLineReading:
        """The line the lab prints next at ``recipe`` (3,) had it stopped after test ``stop``:
        a replay of the run's first ``stop`` tests on a new printer of the same seed, then
        the recipe (module docstring). Evaluation only: neither the bring-up nor the run's
        printer is touched."""
        tests = self.bringup.tests
        if not 0 <= stop <= len(tests):
            raise ValueError(f"stop = {stop}: the run has {len(tests)} tests")
        printer = self._new_printer()
        for k, t in enumerate(tests[:stop], 1):
            r = self._print_line(printer, [t[n] for n in TEST_INPUTS[:3]])
            replayed = (r.linewidth_um, r.true_linewidth_um, r.true_overspray_um)
            run = (t["linewidth_um"], t["true_linewidth_um"], t["true_overspray_um"])
            if not np.allclose(replayed, run, rtol=1e-9, atol=0.0):
                raise RuntimeError(
                    f"the replay of test {k} read {replayed}, the run {run}: the virtual "
                    "printer is not a function of its seed and commands"
                )
        return self._print_line(printer, recipe)


def run_twin(lab: VirtualLab) -> dict:
    """The twin's bring-up until it stops or the budget is spent."""
    b = lab.bringup
    for _ in range(MAX_TESTS + 1):
        decision = b.decide()
        if decision.kind != "test" or len(b.tests) >= MAX_TESTS:
            break
        lab.print([decision.test[n] for n in TEST_INPUTS])
    if decision.kind == "done":
        r = decision.recipe
        return {
            "kind": "done",
            "recipe": [r[n] for n in TEST_INPUTS[:3]],
            "probability": r["probability"],
            "predicted_linewidth_um": [r["linewidth_um"], r["linewidth_2sd_um"]],
        }
    return {"kind": decision.kind}


def _confirmed(lab: VirtualLab) -> dict | None:
    """A stop by the reading rule at the newest test, or None."""
    b = lab.bringup
    rep = float(b.settings["test_line"]["repeatability_relative"])
    t = b.tests[-1]
    if reading_feasibility(t, b.goal, rep) >= b.goal.probability:
        return {"kind": "done", "recipe": [t[n] for n in TEST_INPUTS[:3]]}
    return None


def _objective(test: dict, goal: Goal) -> float:
    excess = max(0.0, test["overspray_um"] / goal.max_overspray_um - 1.0)
    return (
        (test["linewidth_um"] - goal.target_linewidth_um) / goal.tolerance_um
    ) ** 2 + 25 * excess**2


def run_bo(lab: VirtualLab, seed: int) -> dict:
    """scikit-optimize's GP minimiser of the module docstring's objective."""
    # lazy: scikit-optimize is the study's optional extra (``[study]``), not the library's
    from skopt import Optimizer

    box = lab.bringup.box
    opt = Optimizer(
        [tuple(b) for b in box.bounds],
        base_estimator="GP",
        acq_func="EI",
        n_initial_points=5,
        initial_point_generator="lhs",
        random_state=seed,
    )
    for _ in range(MAX_TESTS):
        x = opt.ask()
        test = lab.print(np.round(np.asarray(x, dtype=float) / [1.0, 0.1, 0.1]) * [1.0, 0.1, 0.1])
        stop = _confirmed(lab)
        if stop:
            return stop
        opt.tell(x, _objective(test, lab.bringup.goal))
    return {"kind": "not found"}


def box_behnken(box: InputBox) -> np.ndarray:
    """The 13 runs of a three-factor Box–Behnken design (edge midpoints and the centre)."""
    runs = [[0.5, 0.5, 0.5]]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for a in (0.0, 1.0):
            for b in (0.0, 1.0):
                z = [0.5, 0.5, 0.5]
                z[i], z[j] = a, b
                runs.append(z)
    return box.inputs(np.array(runs))[:, :3]


def _quadratic(z) -> np.ndarray:
    z = np.atleast_2d(z)
    cols = [np.ones(len(z))] + [z[:, i] for i in range(3)]
    cols += [z[:, i] * z[:, j] for i in range(3) for j in range(i, 3)]
    return np.column_stack(cols)


def run_grid(lab: VirtualLab) -> dict:
    """The Box–Behnken design, then the response surface's best inputs, refitted."""
    b = lab.bringup
    for u in box_behnken(b.box):
        lab.print(u)
        stop = _confirmed(lab)
        if stop:
            return stop
    pool = b.box.inputs(qmc.Sobol(3, scramble=True, seed=5).random(4096))
    while len(b.tests) < MAX_TESTS:
        x = b.box.scaled(np.array([[t[n] for n in TEST_INPUTS] for t in b.tests]))
        fits = [
            np.linalg.lstsq(
                _quadratic(x), np.log([t[f"{k}_um"] + 1.0 for t in b.tests]), rcond=None
            )[0]
            for k in ("linewidth", "overspray")
        ]
        design = _quadratic(b.box.scaled(pool))
        w, o = (np.exp(design @ f) - 1.0 for f in fits)
        miss = np.abs(w - b.goal.target_linewidth_um) + 10 * np.maximum(
            o - b.goal.max_overspray_um, 0
        )
        lab.print(np.round(pool[np.argmin(miss), :3] / [1.0, 0.1, 0.1]) * [1.0, 0.1, 0.1])
        stop = _confirmed(lab)
        if stop:
            return stop
    return {"kind": "not found"}


def meets_goal(goal: Goal, linewidth_um: float, overspray_um: float) -> bool:
    """Whether a line is within ± tolerance of the target with L_o ≤ max."""
    return bool(
        abs(linewidth_um - goal.target_linewidth_um) <= goal.tolerance_um
        and overspray_um <= goal.max_overspray_um
    )


def evaluate(lab: VirtualLab, outcome: dict, n_tests: int) -> dict:
    """An outcome stopped after test ``n_tests`` of the lab's run, against the truth: the
    line the lab prints next at its recipe (``holds``), the ink's line at the nominal machine
    state (``holds_nominal``) and after ± 5 % droplet size and aerosol density."""
    ink, goal = lab.ink, lab.bringup.goal
    out = {**outcome, "tests": n_tests}
    if outcome["kind"] != "done":
        return out
    nxt = lab.next_print(outcome["recipe"], n_tests)
    out["next_linewidth_um"] = nxt.true_linewidth_um
    out["next_overspray_um"] = nxt.true_overspray_um
    out["holds"] = meets_goal(goal, nxt.true_linewidth_um, nxt.true_overspray_um)
    u = np.array([outcome["recipe"]])
    w, o = settled_line(ink, u, SPEED_MM_S)
    out["nominal_linewidth_um"], out["nominal_overspray_um"] = float(w[0]), float(o[0])
    out["holds_nominal"] = meets_goal(goal, float(w[0]), float(o[0]))
    moved = [
        float(settled_line(ink, u, SPEED_MM_S, droplet_scale=ds, aerosol_scale=As)[0][0])
        for ds, As in ((1.05, 1.0), (0.95, 1.0), (1.0, 1.05), (1.0, 0.95))
    ]
    out["robust_linewidth_um"] = moved
    out["robust_worst_miss_um"] = float(max(abs(m - goal.target_linewidth_um) for m in moved))
    out["robust_holds"] = bool(out["robust_worst_miss_um"] <= goal.tolerance_um)
    return out


def run_ink(seed: int, generator: str, methods, out_of_reach: bool = False) -> dict:
    """Every method on one ink (the same printer seed for each)."""
    ink = draw_ink(seed, generator)
    goal = goal_for(ink, out_of_reach)
    box = InputBox.from_limits(None, SPEED_MM_S)
    row = {"ink": ink.as_dict(), "goal": goal.__dict__, "out_of_reach": out_of_reach}
    for method in methods:
        lab = VirtualLab(ink, 500 + seed, BringUp.create(goal, box))
        t0 = time.perf_counter()
        if method == "twin":
            outcome = run_twin(lab)
        elif method == "bo":
            outcome = run_bo(lab, seed)
        else:
            outcome = run_grid(lab)
        wall_s = time.perf_counter() - t0  # the method's own time, not its judgement's
        result = evaluate(lab, outcome, len(lab.bringup.tests))
        result["wall_s"] = wall_s
        result["readings"] = [
            {k: t[k] for k in (*TEST_INPUTS, "linewidth_um", "overspray_um", "true_linewidth_um")}
            for t in lab.bringup.tests
        ]
        row[method] = result
        if method != "twin":
            lenient = _first_in_tolerance(lab.bringup.tests, goal)
            row[f"{method}{LENIENT}"] = evaluate(lab, lenient, lenient.pop("tests"))
    return row


#: the suffix of a baseline stopped by the lenient rule (a reading within tolerance)
LENIENT = " (reading in tolerance)"


def _first_in_tolerance(tests: list, goal: Goal) -> dict:
    """The lenient stop: the first reading within ± tolerance of the target with L_o ≤ max
    (what a lab does without a model; the same run, so the path up to it is the method's)."""
    for k, t in enumerate(tests, 1):
        if meets_goal(goal, t["linewidth_um"], t["overspray_um"]):
            return {"kind": "done", "recipe": [t[n] for n in TEST_INPUTS[:3]], "tests": k}
    return {"kind": "not found", "tests": len(tests)}


def _tests_until_holding(results: list, rule: str) -> np.ndarray:
    """Tests until a recipe that holds by ``rule`` (``holds`` or ``holds_nominal``); a recipe
    that does not hold, or none, counts as ``MAX_TESTS + 1``."""
    return np.array([r["tests"] if r.get(rule) else MAX_TESTS + 1 for r in results])


def summarise(rows: list, methods) -> dict:
    """Per generator and method: the figures of the module docstring (``holds``: the next
    print; ``…_nominal``: at the nominal machine state)."""
    out = {}
    for generator in sorted({r["ink"]["generator"] for r in rows}):
        reach = [r for r in rows if r["ink"]["generator"] == generator and not r["out_of_reach"]]
        beyond = [r for r in rows if r["ink"]["generator"] == generator and r["out_of_reach"]]
        for method in methods:
            results = [r[method] for r in reach]
            counts = _tests_until_holding(results, "holds")
            nominal = _tests_until_holding(results, "holds_nominal")
            done = [d for d in results if d["kind"] == "done"]
            out[f"{generator}/{method}"] = {
                "inks": len(reach),
                "median_tests": float(np.median(counts)) if len(counts) else None,
                "p90_tests": float(np.percentile(counts, 90)) if len(counts) else None,
                "done_within_12": float(np.mean(counts <= 12)) if len(counts) else None,
                "silent_misses": int(sum(not d["holds"] for d in done)),
                "recipes": len(done),
                "median_tests_nominal": float(np.median(nominal)) if len(nominal) else None,
                "p90_tests_nominal": float(np.percentile(nominal, 90)) if len(nominal) else None,
                "done_within_12_nominal": float(np.mean(nominal <= 12)) if len(nominal) else None,
                "silent_misses_nominal": int(sum(not d["holds_nominal"] for d in done)),
                "holds_nominal": float(np.mean([d["holds_nominal"] for d in done]))
                if done
                else None,
                # what the method claimed of its recipes (the twin: P(holds)), against the share
                # that held: P ≥ 0.9 per recipe allows up to 1 miss in 10
                "claimed_probability_mean": float(np.mean([d["probability"] for d in done]))
                if done and all("probability" in d for d in done)
                else None,
                "robust_holds": float(np.mean([d["robust_holds"] for d in done])) if done else None,
                "robust_worst_miss_um_median": float(
                    np.median([d["robust_worst_miss_um"] for d in done])
                )
                if done
                else None,
                "out_of_reach_inks": len(beyond),
                "out_of_reach_said": int(sum(r[method]["kind"] == "out_of_reach" for r in beyond)),
                "out_of_reach_recipe_given": int(sum(r[method]["kind"] == "done" for r in beyond)),
                "out_of_reach_mean_tests": float(np.mean([r[method]["tests"] for r in beyond]))
                if beyond
                else None,
            }
    return out


def run_study(
    inks: int = 20,
    first: int = 2000,
    methods=("twin", "bo", "grid"),
    out_of_reach: int = 5,
    progress=print,
) -> dict:
    """The whole comparison (module docstring): ``inks`` held-out inks per generator from seed
    ``first``, plus ``out_of_reach`` inks per generator with an unreachable target."""
    t0 = time.perf_counter()
    rows = []
    reported = [m for m in methods] + [f"{m}{LENIENT}" for m in methods if m != "twin"]
    for generator in ("model", "alt"):
        for k in range(inks + out_of_reach):
            row = run_ink(first + k, generator, methods, out_of_reach=k >= inks)
            rows.append(row)
            progress(
                f"{generator} ink {first + k}{' (out of reach)' if row['out_of_reach'] else ''}: "
                + ", ".join(f"{m} {row[m]['kind']} after {row[m]['tests']}" for m in methods)
            )
    return {"rows": rows, "summary": summarise(rows, reported), "wall_s": time.perf_counter() - t0}


def markdown(results: dict, command: str) -> str:
    """The study's table: the next print's figures, then the nominal state's."""
    lines = [
        f"Command: `{command}` ({results['wall_s']:.0f} s)",
        "",
        "Holds: the line printed next at the recipe is within ± 2 µm with L_o ≤ max; at the "
        "nominal state: the ink's settled line at the machine's nominal droplet size and "
        "aerosol density.",
        "",
        "| generator / method | inks | median tests | 90th pct | done ≤ 12 | silent misses "
        "(claimed P mean) | at nominal: done ≤ 12 | at nominal: silent misses, recipes "
        "holding | robust (±5 %) | out of reach said / recipe given |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, s in results["summary"].items():
        robust = "–" if s["robust_holds"] is None else f"{100 * s['robust_holds']:.0f} %"
        claimed = s.get("claimed_probability_mean")
        claimed = "" if claimed is None else f" ({claimed:.3f})"
        held = s["recipes"] - s["silent_misses_nominal"]
        lines.append(
            f"| {key} | {s['inks']} | {s['median_tests']:g} | {s['p90_tests']:g} | "
            f"{100 * s['done_within_12']:.0f} % | {s['silent_misses']}{claimed} | "
            f"{100 * s['done_within_12_nominal']:.0f} % | "
            f"{s['silent_misses_nominal']}, {held}/{s['recipes']} | {robust} | "
            f"{s['out_of_reach_said']}/{s['out_of_reach_inks']} said, "
            f"{s['out_of_reach_recipe_given']} recipe |"
        )
    return "\n".join(lines) + "\n"


def _argument(name: str, default):
    if name in sys.argv:
        return type(default)(sys.argv[sys.argv.index(name) + 1])
    return default


if __name__ == "__main__":
    n_inks = _argument("--inks", 20)
    first_seed = _argument("--first", 2000)
    chosen = tuple(_argument("--methods", "twin,bo,grid").split(","))
    n_beyond = _argument("--out-of-reach", 5)
    OUT.mkdir(parents=True, exist_ok=True)
    results = run_study(n_inks, first_seed, chosen, n_beyond)
    cmd = (
        f"python -m ajtwin.studies.develop --inks {n_inks} --first {first_seed} "
        f"--methods {','.join(chosen)} --out-of-reach {n_beyond}"
    )
    (OUT / "results.json").write_text(json.dumps(results, indent=1, default=float))
    (OUT / "results.md").write_text(markdown(results, cmd))
    print(markdown(results, cmd))
