"""Where the exp3 L_o forecast error comes from (L_o's ±2σ band on the alt generator).

For each seed: the calibrated forecast (input_following, EM on t < 37.6 min) against the
noise-free truth, split into the part due to the line coefficients (the twin's nominal g
vs the virtual printer's true coefficients, on the twin's states) and the part due to the
forecast states (true coefficients, twin states vs true states); then the L_o RMS with one
state at a time replaced by its truth, which names the state that carries the error.

    python -m ajtwin.studies.forecast_lo_diagnosis [--seeds 2,5] [--truth model,alt]
"""

import argparse

import numpy as np

from ajtwin.apps.planning.forecast import forecast
from ajtwin.estimation import Twin
from ajtwin.estimation.em import EMSettings, run_em
from ajtwin.model.names import STATE_NAMES
from ajtwin.model.system import output_function
from ajtwin.simulation import run_virtual_print
from ajtwin.studies.experiments import EXP3_CALIBRATION_END_S


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.asarray(a) ** 2)))


def diagnose(seed: int, truth: str) -> dict:
    """Where exp3's overspray forecast error comes from on one seed: state, θ and output terms."""
    vp = run_virtual_print("exp3", seed, truth_generator=truth)
    rec, n = vp.record, int(EXP3_CALIBRATION_END_S)
    twin = Twin.default(em=False, transition="input_following")
    model_inputs = twin.model_inputs(rec.inputs)
    cal = twin.run(inputs=rec.inputs[:n], measurements=rec.outputs[:n], time_s=rec.time_s[:n])
    em = run_em(
        twin.spec, cal.start_mean, cal.start_cov, model_inputs[:n], rec.outputs[:n],
        np.zeros(5), twin.process_cov, twin.measurement_var,
        settings=EMSettings(twin.theta_prior_precision, 10, 1e-6),
        functions=twin.functions,
    )  # fmt: skip
    fc = forecast(
        twin, np.asarray(em.filtered.means[-1]), np.asarray(em.filtered.covariances[-1]),
        rec.inputs[n - 1 : -1], em.theta, input_response0=float(model_inputs[n - 1, -1]),
    )  # fmt: skip
    params, u = twin.model.params, rec.inputs[n:]
    x_twin, x_true = fc.state_means, vp.states[n:]

    def overspray(x, coefficients):
        return np.asarray(output_function(x, u, params, coefficients))[:, 1]

    y_true = vp.outputs_true[n:, 1]
    y_twin = overspray(x_twin, twin.model.coefficient_matrix)
    y_true_coef = overspray(x_twin, vp.line_coefficients)
    one_state_true = {}
    for i, name in enumerate(STATE_NAMES):
        x = np.array(x_twin)
        x[:, i] = x_true[:, i]
        one_state_true[name] = round(_rms(overspray(x, vp.line_coefficients) - y_true), 3)
    inside = np.abs(y_twin - y_true) <= 2 * fc.output_stds[:, 1]
    relative = np.mean((x_twin - x_true) / np.abs(x_true).clip(1e-30), axis=0)
    return {
        "truth": truth,
        "seed": seed,
        "overspray_rmse_um": round(_rms(y_twin - y_true), 3),
        "overspray_mean_error_um": round(float(np.mean(y_twin - y_true)), 3),
        "band_coverage": round(float(np.mean(inside)), 3),
        "coefficient_part_rms_um": round(_rms(y_twin - y_true_coef), 3),
        "state_part_rms_um": round(_rms(y_true_coef - y_true), 3),
        "rmse_with_one_state_true_um": one_state_true,
        "mean_relative_state_error": dict(zip(STATE_NAMES, np.round(relative, 3).tolist())),
    }


def main() -> list:
    """Run the diagnosis for the seeds and generators on the command line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="2,5")
    parser.add_argument("--truth", default="model,alt")
    args = parser.parse_args()
    rows = [
        diagnose(int(seed), truth)
        for truth in args.truth.split(",")
        for seed in args.seeds.split(",")
    ]
    for row in rows:
        print(row)
    return rows


if __name__ == "__main__":
    main()
