"""Why MPC on the twin is ~1× PI on the virtual printer: the measurement noise sets the floor.

    python -m ajtwin.studies.control_limits [--seeds 1-5] [--minutes 45] [--out F.json]

Runs PI and the MPC on the twin in closed loop on exp1 (target 65 µm) four times over the
same seeds, removing one source of noise at a time from the virtual printer
(``overrides={"measurement": …}``, nothing else changes):

* ``default``        — the printer as the comparison runs it;
* ``no_jitter``      — the MFCs and the atomizer current hold their set-points exactly
  (``*_jitter_* = 0``: the true flows otherwise wander 0.15 sccm / 1 mA around the
  set-point with a 5 s correlation, faster than a 10 s control period can follow);
* ``no_line_noise``  — the camera reads the true line (``linewidth_log_sd`` 1e-4 instead
  of 0.04: ~2.6 µm per sample at 65 µm, the only feedback PI has);
* ``neither``        — both removed.

and prints RMS error of the true L_w to the target (after the 60 s warm-up), per case
and strategy, with the ratio PI/twin. The controllers are unchanged (same tuning, the
twin's noise model unchanged): the question is how much of the error is the printer's
noise that no set-point loop can remove. Not part of ``make bench`` (minutes of CPU).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from ajtwin.apps.planning.strategies import start_inputs
from ajtwin.estimation import Twin
from ajtwin.studies.closed_loop import ClosedLoopPlan, simulate_strategy

CASES = {
    "default": {},
    "no_jitter": {
        "carrier_flow_jitter_sccm": 0.0,
        "sheath_flow_jitter_sccm": 0.0,
        "atomizer_current_jitter_mA": 0.0,
    },
    "no_line_noise": {"linewidth_log_sd": 1e-4},
}
CASES["neither"] = {**CASES["no_jitter"], **CASES["no_line_noise"]}
STRATEGIES = ("pi", "mpc_twin")


def main(seeds=(1, 2, 3), minutes: float = 45.0, target: float = 65.0) -> dict:
    """Every strategy on clean prints under the measurement cases: rms error, holds, limits.

    Parameters
    ----------
    seeds : tuple of int
    minutes : float
        Print length [min].
    target : float
        Target linewidth [µm].
    """
    u0, _ = start_inputs(Twin.default(), target)
    out: dict = {"seeds": list(seeds), "minutes": minutes, "target_um": target, "cases": {}}
    for case, measurement in CASES.items():
        overrides = {"measurement": measurement} if measurement else None
        rows = {s: [] for s in STRATEGIES}
        t0 = time.process_time()
        for seed in seeds:
            for strategy in STRATEGIES:
                plan = ClosedLoopPlan(
                    "exp1", int(seed), target, duration_min=minutes, u0=u0, overrides=overrides
                )
                run = simulate_strategy(plan, strategy)
                rows[strategy].append(run.metrics["rms_error_um"])
        entry = {f"{s}_rms_um_per_seed": [round(v, 4) for v in rows[s]] for s in STRATEGIES}
        for s in STRATEGIES:
            entry[f"{s}_rms_um_mean"] = round(float(np.mean(rows[s])), 4)
        entry["ratio_pi_over_mpc_twin"] = round(
            float(np.mean(rows["pi"]) / np.mean(rows["mpc_twin"])), 3
        )
        entry["cpu_s"] = round(time.process_time() - t0, 1)
        out["cases"][case] = entry
        print(
            f"{case:14s} PI {entry['pi_rms_um_mean']:.3f} µm  twin "
            f"{entry['mpc_twin_rms_um_mean']:.3f} µm  "
            f"PI/twin {entry['ratio_pi_over_mpc_twin']:.2f}×"
            f"  ({entry['cpu_s']:.0f} s CPU)",
            flush=True,
        )
    return out


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = (int(v) for v in text.split("-", 1))
        return list(range(a, b + 1))
    return [int(v) for v in text.split(",")]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-3")
    parser.add_argument("--minutes", type=float, default=45.0)
    parser.add_argument("--out", default=None, help="write the figures as JSON here")
    args = parser.parse_args()
    figures = main(_seeds(args.seeds), args.minutes)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(figures, fh, indent=2)
