"""Where a commissioned twin's ±2σ band comes from: the filter's σ vs the calibration term.

Per machine (as :mod:`ajtwin.studies.machine`: 20-min commissioning print, d_a known ±0.1 µm, then
the
next 90-min exp1 print run by the calibrated twin), per state: the median total σ, its
filter part and its calibration part C_k = A Σ_c Aᵀ (``run.calibration_covariances``,
:mod:`ajtwin.estimation.calibration_uncertainty`), the rms error, and the rms z with the
total σ and with the filter's σ alone. rms z ≈ 1 is an honest band.

    python -m ajtwin.studies.band_breakdown --truth model --machines 1006,1007,1008
"""

from __future__ import annotations

import argparse

import numpy as np

from ajtwin.engine.commissioning import calibrated_twin, commissioned_start
from ajtwin.simulation.printer import run_virtual_print
from ajtwin.studies.machine import commission_virtual_machine, print_seed_of

STATES = {"d_a": 0, "V_l": 1, "ΔR_N": 3, "φ_A": 4}


def breakdown(machine_seed: int, truth: str) -> dict:
    """Per state: the σ of the filter and of the calibration, the error and z of a commissioned
    machine's next print."""
    print_seed = print_seed_of(machine_seed)
    comm, done, _ = commission_virtual_machine(
        print_seed, truth, machine_seed=machine_seed, learn_noise_scale=False
    )
    result = done.result
    nxt = run_virtual_print(
        "exp1",
        seed=print_seed + 1,
        duration_min=90,
        continue_from=comm.record,
        truth_generator=truth,
    )
    twin = calibrated_twin(result)
    run = twin.run(nxt.record, start=commissioned_start(result))
    total = run.stds
    calibration = np.sqrt(np.maximum(np.diagonal(run.calibration_covariances, 0, 1, 2), 0.0))
    error = run.means - nxt.states
    out = {}
    for name, i in STATES.items():
        filt = np.sqrt(np.maximum(total[:, i] ** 2 - calibration[:, i] ** 2, 1e-300))
        out[name] = {
            "median_sigma": float(np.median(total[:, i])),
            "median_sigma_filter": float(np.median(filt)),
            "median_sigma_calibration": float(np.median(calibration[:, i])),
            "rms_error": float(np.sqrt(np.mean(error[:, i] ** 2))),
            "rms_z": float(np.sqrt(np.mean((error[:, i] / total[:, i]) ** 2))),
            "rms_z_filter_only": float(np.sqrt(np.mean((error[:, i] / filt) ** 2))),
        }
    return out


def main(argv=None) -> None:
    """Print the breakdown for the machines given on the command line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truth", choices=("model", "alt"), default="model")
    parser.add_argument("--machines", default="1006,1007,1008")
    args = parser.parse_args(argv)
    print("machine state  σ median (filter, calibration)  rms error  rms z (filter only)")
    for seed in (int(s) for s in args.machines.split(",")):
        for name, r in breakdown(seed, args.truth).items():
            print(
                f"{seed} {name:5s} {r['median_sigma']:.3g} ({r['median_sigma_filter']:.3g}, "
                f"{r['median_sigma_calibration']:.3g})  {r['rms_error']:.3g}  "
                f"{r['rms_z']:.2f} ({r['rms_z_filter_only']:.2f})"
            )


if __name__ == "__main__":
    main()
