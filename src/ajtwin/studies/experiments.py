"""The paper's three experiments (§8, App. F–H) on virtual-printer prints.

* ``exp1`` — constant inputs: open loop vs closed loop (EKF + EM) with ±2σ and
  the truth at 30/60/90 min, output percentage errors, the EKF-alone ablation
  (App. G) and the θ trajectories.
* ``exp2`` — input steps: the inferred states explain the output drift; the
  change of L_w between steady stretches is split into the states' and the
  inputs' contributions through the output model.
* ``exp3`` — θ calibrated by EM on t < 37.6 min, then an open-loop forecast of
  L_w, L_o afterwards: calibrated vs uncalibrated vs truth.

The virtual printer's truth is not the twin's model (model reference §10), so these
figures measure the twin against something it does not contain.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import median_filter

from ajtwin.apps.planning.forecast import forecast
from ajtwin.estimation.em import EMSettings, run_em
from ajtwin.estimation.twin import Twin, TwinRun
from ajtwin.model import OUTPUT_NAMES, STATE_NAMES
from ajtwin.simulation import run_virtual_print, simulate, truth_alt
from ajtwin.simulation.printer import first_order_lag
from ajtwin.units import um_to_nm

CHECK_MINUTES = (30, 60, 90)
#: states whose closed-loop error is judged relative to truth (model reference §10)
RELATIVE_STATES = (0, 1, 4)
NOZZLE = 3
EXP3_CALIBRATION_END_S = 37.6 * 60


def _check_indices(n_steps):
    return [min(int(m * 60), n_steps - 1) for m in CHECK_MINUTES]


def state_errors(means, truth) -> dict:
    """Errors at 30/60/90 min: relative (%) for d_a, V_l, φ_A; nm for ΔR_N; µm for ΔR_T."""
    out = {}
    for minute, k in zip(CHECK_MINUTES, _check_indices(len(truth))):
        row = {}
        for i in RELATIVE_STATES:
            row[STATE_NAMES[i] + "_rel_pct"] = float(
                100 * abs(means[k, i] - truth[k, i]) / abs(truth[k, i])
            )
        row["nozzle_deposition_abs_nm"] = float(um_to_nm(abs(means[k, NOZZLE] - truth[k, NOZZLE])))
        row["tube_deposition_abs_um"] = float(abs(means[k, 2] - truth[k, 2]))
        out[f"{minute}min"] = row
    return out


def coverage(means, stds, truth, skip_s: int = 0) -> dict:
    """Fraction of steps with the truth inside ±2σ, per state."""
    inside = np.abs(means[skip_s:] - truth[skip_s:]) <= 2 * stds[skip_s:]
    return {name: float(inside[:, i].mean()) for i, name in enumerate(STATE_NAMES)}


def output_percentage_errors(run: TwinRun, measured) -> dict:
    """Mean absolute % error of the one-step predicted outputs vs the measurements."""
    pred = np.asarray(run.filtered.predicted_outputs)
    with np.errstate(invalid="ignore", divide="ignore"):
        pct = 100 * np.abs(pred - measured) / np.abs(measured)
    return {name: float(np.nanmean(pct[:, i])) for i, name in enumerate(OUTPUT_NAMES)}


def open_loop_from_start(twin: Twin, run: TwinRun, inputs) -> np.ndarray:
    """The static physics model from the fitted start state, θ = 0 (paper: 'open loop')."""
    return twin.model.simulate(run.start_mean, inputs[:-1])


# --------------------------------------------------------------------------- #
def run_exp1(seed: int, twin_overrides: dict | None = None):
    """Exp 1 on one seed: the twin with and without EM against the truth.

    Returns (record, runs, metrics).
    """
    record = simulate("exp1", seed)
    truth = record.true_states
    timings = {}
    t0 = time.perf_counter()
    em_run = Twin.default(**(twin_overrides or {})).run(record)
    timings["ekf_em_s"] = time.perf_counter() - t0
    twin_ekf = Twin.default(em=False, **(twin_overrides or {}))
    t0 = time.perf_counter()
    ekf_run = twin_ekf.run(record)
    timings["ekf_only_s"] = time.perf_counter() - t0
    open_loop = open_loop_from_start(twin_ekf, ekf_run, record.inputs)
    metrics = {
        "seed": seed,
        "closed_loop_em": state_errors(em_run.means, truth),
        "closed_loop_ekf_only": state_errors(ekf_run.means, truth),
        "open_loop": state_errors(open_loop, truth),
        "coverage_em": coverage(em_run.means, em_run.stds, truth),
        "coverage_ekf_only": coverage(ekf_run.means, ekf_run.stds, truth),
        "output_mape_pct": output_percentage_errors(em_run, record.outputs),
        "final_theta": dict(
            zip(
                STATE_NAMES,
                map(float, em_run.theta_history.iloc[-1][[f"theta_{n}" for n in STATE_NAMES]]),
            )
        )
        if len(em_run.theta_history)
        else {},
        "reinitialisations": int(np.asarray(em_run.filtered.reinitialised).sum()),
        "timings_s": timings,
    }
    return record, {"em": em_run, "ekf": ekf_run, "open_loop": open_loop}, metrics


def run_exp2(seed: int, twin_overrides: dict | None = None):
    """Exp 2 on one seed: input steps, the twin's states and the explained linewidth changes."""
    record = simulate("exp2", seed)
    truth = record.true_states
    twin = Twin.default(**(twin_overrides or {}))
    run = twin.run(record)
    metrics = {
        "seed": seed,
        "closed_loop_em": state_errors(run.means, truth),
        "coverage_em": coverage(run.means, run.stds, truth),
        "output_mape_pct": output_percentage_errors(run, record.outputs),
        "linewidth_drift_explained": explain_linewidth_changes(twin, run, record),
    }
    return record, {"em": run}, metrics


def explain_linewidth_changes(twin: Twin, run: TwinRun, record, span_s: int = 300) -> list:
    """Split the L_w change between consecutive steady stretches into contributions.

    For each input step (and the print's start → end) the change of the
    predicted L_w is written as Σ (coefficient × change of a state or input)
    through the output model, with the nozzle term evaluated exactly.
    """
    inputs = record.inputs
    changed = np.flatnonzero(np.any(np.abs(np.diff(setpoints(inputs), axis=0)) > 0.5, axis=1))
    # one set-point change shows as a few adjacent indices after the median filter: keep the first
    steps = [int(k) + 1 for n, k in enumerate(changed) if n == 0 or k - changed[n - 1] > 120]
    edges = [0, *steps, len(inputs)]
    coeff = twin.model.coefficients.linewidth
    means = run.means
    out = []
    for a, b in zip(edges[:-2], edges[1:-1]):
        c = edges[edges.index(b) + 1]
        before = slice(max(a, b - span_s), b)
        after = slice(max(b, c - span_s), c)
        x0, x1 = means[before].mean(axis=0), means[after].mean(axis=0)
        u0, u1 = inputs[before].mean(axis=0), inputs[after].mean(axis=0)

        def nozzle(n):
            return n * (
                coeff.nozzle_deposition_1
                + n * (coeff.nozzle_deposition_2 + n * coeff.nozzle_deposition_3)
            )

        parts = {
            "droplet_diameter": coeff.droplet_diameter * (x1[0] - x0[0]),
            "aerosol_fraction": coeff.aerosol_fraction * (x1[4] - x0[4]),
            "nozzle_deposition": nozzle(x1[3]) - nozzle(x0[3]),
            "carrier_flow": coeff.carrier_flow * (u1[1] - u0[1]),
            "sheath_flow": coeff.sheath_flow * (u1[2] - u0[2]),
        }
        measured = record.outputs[:, 0]
        out.append(
            {
                "from_s": float(before.start),
                "to_s": float(after.stop),
                "measured_change_um": float(
                    np.nanmean(measured[after]) - np.nanmean(measured[before])
                ),
                "explained_change_um": float(sum(parts.values())),
                "contributions_um": {k: float(v) for k, v in parts.items()},
            }
        )
    return out


def setpoints(inputs, width: int = 61):
    """Median-filtered inputs (MFC jitter removed) to locate set-point steps."""
    return median_filter(inputs, size=(width, 1), mode="nearest")


def droplet_oracle_forecast(vp, start: int, truth: str = "model") -> np.ndarray:
    """The best forecast of the true d_a for t > ``start`` that any model could make.

    Uses the virtual printer's own droplet law (known only to the simulator): the
    deterministic parts (the input response through the generator's lags, the levelling
    trend) exactly, the random part by its conditional mean given the truth at ``start``
    (an OU wander decays toward 0; a random walk with jumps stays). What is left, the
    wander's innovations after ``start``, no forecast from data up to ``start`` can know.

    Returns d_a (T − start − 1,) for t = start + 1 … T − 1 [µm].
    """

    droplet = np.asarray(vp.processes.droplet_um, dtype=float)
    u = vp.processes.mfc_inputs
    n = len(droplet)
    t = np.arange(n, dtype=float)
    h = t[start + 1 :] - start
    if truth == "alt":
        d = truth_alt.load_alt_settings()["droplet"]
        target = d["carrier_um_per_sccm"] * (u[:, 1] - 23.0) + d["current_um_per_mA"] * (
            u[:, 0] - 375.0
        )
        response = truth_alt.lag_filter(truth_alt.lag_filter(target, d["lag_s"][0]), d["lag_s"][1])
        return droplet[start] + response[start + 1 :] - response[start]
    cfg = vp.scenario.config["truth"]
    target = cfg["droplet_carrier_um_per_sccm"] * (
        u[:, 1] - cfg["droplet_reference_carrier_sccm"]
    ) + cfg["droplet_current_um_per_mA"] * (u[:, 0] - cfg["droplet_reference_current_mA"])
    shift = first_order_lag(target, cfg["droplet_input_lag_s"])
    rate = vp.processes.draws["droplet_trend_um_per_h"] / 3600.0
    tau = cfg["droplet_trend_time_s"]
    trend = rate * tau * -np.expm1(-t / tau) if tau > 0 else rate * t
    known = trend + shift
    wander_now = droplet[start] - known[start] - (vp.processes.draws["droplet_start_um"] - shift[0])
    decay = np.exp(-h / cfg["droplet_ou_time_s"]) if cfg["droplet_ou_time_s"] > 0 else 0.0 * h
    return droplet[start] - known[start] - wander_now + known[start + 1 :] + wander_now * decay


def forecast_band_coverage(y_forecast, y_std, y_true) -> float:
    """Fraction of the horizon with the noise-free truth inside the forecast's ±2σ."""
    return float(np.mean(np.abs(y_forecast - y_true) <= 2.0 * y_std))


def run_exp3(
    seed: int,
    twin_overrides: dict | None = None,
    em_iterations: int = 10,
    truth: str = "model",
):
    """Exp 3 on one seed: EM on t < 37.6 min, open-loop forecast of L_w, L_o afterwards.

    Three forecasts of the noise-free true outputs after 37.6 min:

    * calibrated — the twin (its transition variant) from the EM-filtered state at 37.6 min
      with θ from EM, with its ±2σ band (:func:`ajtwin.apps.planning.forecast.forecast`);
    * θ withheld — the same twin and filtered state, θ = 0 (what θ adds);
    * uncalibrated — the paper's baseline: the static physics model (paper transition,
      θ = 0) open loop from the fitted start state at t = 0.

    ``truth`` picks the virtual printer's generator: ``"model"`` (default) or ``"alt"``
    (:mod:`ajtwin.simulation.truth_alt`, evaluation only).
    """

    vp = run_virtual_print("exp3", seed, truth_generator=truth)
    record = vp.record
    n_cal = int(EXP3_CALIBRATION_END_S)
    twin = Twin.default(em=False, **(twin_overrides or {}))
    # inputs as the twin's transition reads them (a variant may add the input response)
    model_inputs = twin.model_inputs(record.inputs)
    response_at_start = float(model_inputs[n_cal - 1, -1]) if model_inputs.shape[1] > 3 else None
    calibration = twin.run(
        inputs=record.inputs[:n_cal],
        measurements=record.outputs[:n_cal],
        time_s=record.time_s[:n_cal],
    )
    # EM on the whole calibration stretch (paper: calibrate θ on t < 37.6 min)
    t0 = time.perf_counter()
    em = run_em(
        twin.spec,
        calibration.start_mean,
        calibration.start_cov,
        model_inputs[:n_cal],
        record.outputs[:n_cal],
        np.zeros(5),
        twin.process_cov,
        twin.measurement_var,
        settings=EMSettings(twin.theta_prior_precision, em_iterations, 1e-6),
        functions=twin.functions,
    )
    em_seconds = time.perf_counter() - t0
    theta = em.theta
    start_cal = np.asarray(em.filtered.means[-1])
    start_cal_cov = np.asarray(em.filtered.covariances[-1])
    start_uncal = np.asarray(calibration.filtered.means[-1])
    start_uncal_cov = np.asarray(calibration.filtered.covariances[-1])
    future = record.inputs[n_cal - 1 : -1]
    model = twin.model
    fc_cal = forecast(
        twin, start_cal, start_cal_cov, future, theta, input_response0=response_at_start
    )
    # stricter ablation: the same twin and filtered state at 37.6 min, only θ withheld
    fc_theta_only = forecast(
        twin, start_uncal, start_uncal_cov, future, np.zeros(5), input_response0=response_at_start
    )
    x_cal = np.concatenate([start_cal[None], fc_cal.state_means])
    x_theta_only = np.concatenate([start_uncal[None], fc_theta_only.state_means])
    # paper's baseline: the static physics model, open loop from the start (θ = 0, no EKF)
    x_uncal = model.simulate(calibration.start_mean, record.inputs[:-1])[n_cal:]
    # outputs at the inputs of their own second (the forecast's g used the step's input)
    y_cal = model.outputs(fc_cal.state_means, record.inputs[n_cal:])
    y_uncal = model.outputs(x_uncal, record.inputs[n_cal:])
    y_theta_only = model.outputs(fc_theta_only.state_means, record.inputs[n_cal:])
    y_true = vp.outputs_true[n_cal:]
    y_meas = record.outputs[n_cal:]

    def rmse(a, b):
        return float(np.sqrt(np.nanmean((a - b) ** 2)))

    metrics = {
        "seed": seed,
        "truth_generator": truth,
        "transition": twin.config.transition,
        "calibration_end_s": n_cal,
        "theta_calibrated": dict(zip(STATE_NAMES, map(float, theta))),
        "em_iterations": em.iterations,
        "em_seconds": em_seconds,
        "forecast_rmse_vs_noise_free_truth": {
            "linewidth_calibrated_um": rmse(y_cal[:, 0], y_true[:, 0]),
            "linewidth_uncalibrated_um": rmse(y_uncal[:, 0], y_true[:, 0]),
            "overspray_calibrated_um": rmse(y_cal[:, 1], y_true[:, 1]),
            "overspray_uncalibrated_um": rmse(y_uncal[:, 1], y_true[:, 1]),
        },
        "ablation_same_start_state_without_theta_vs_noise_free_truth": {
            "linewidth_um": rmse(y_theta_only[:, 0], y_true[:, 0]),
            "overspray_um": rmse(y_theta_only[:, 1], y_true[:, 1]),
        },
        "forecast_rmse_vs_measured": {
            "linewidth_calibrated_um": rmse(y_cal[:, 0], y_meas[:, 0]),
            "linewidth_uncalibrated_um": rmse(y_uncal[:, 0], y_meas[:, 0]),
            "overspray_calibrated_um": rmse(y_cal[:, 1], y_meas[:, 1]),
            "overspray_uncalibrated_um": rmse(y_uncal[:, 1], y_meas[:, 1]),
        },
        # the ±2σ band of the calibrated forecast (state uncertainty, no sensor noise)
        "forecast_band_coverage": {
            "linewidth": forecast_band_coverage(
                y_cal[:, 0], fc_cal.output_stds[:, 0], y_true[:, 0]
            ),
            "overspray": forecast_band_coverage(
                y_cal[:, 1], fc_cal.output_stds[:, 1], y_true[:, 1]
            ),
        },
        # the d_a part of the error, and what no forecast from the filtered state can know
        "droplet_forecast_rmse_um": {
            "calibrated": rmse(x_cal[1:, 0], vp.states[n_cal:, 0]),
            "theta_withheld": rmse(x_theta_only[1:, 0], vp.states[n_cal:, 0]),
            "uncalibrated": rmse(x_uncal[:, 0], vp.states[n_cal:, 0]),
        },
    }
    # the same forecast with the oracle's d_a: what a perfect droplet law would reach
    x_oracle = np.array(fc_cal.state_means)
    x_oracle[:, 0] = droplet_oracle_forecast(vp, n_cal - 1, truth)
    y_oracle = model.outputs(x_oracle, record.inputs[n_cal:])
    metrics["oracle_droplet_forecast"] = {
        "linewidth_um": rmse(y_oracle[:, 0], y_true[:, 0]),
        "overspray_um": rmse(y_oracle[:, 1], y_true[:, 1]),
        "droplet_um": rmse(x_oracle[:, 0], vp.states[n_cal:, 0]),
    }
    f = metrics["forecast_rmse_vs_noise_free_truth"]
    ablation = metrics["ablation_same_start_state_without_theta_vs_noise_free_truth"]
    for output in ("linewidth", "overspray"):
        metrics[f"{output}_rmse_ratio_calibrated_over_uncalibrated"] = (
            f[f"{output}_calibrated_um"] / f[f"{output}_uncalibrated_um"]
        )
        metrics[f"{output}_rmse_ratio_calibrated_over_theta_withheld"] = (
            f[f"{output}_calibrated_um"] / ablation[f"{output}_um"]
        )
    series = {
        "y_cal": y_cal,
        "y_cal_std": fc_cal.output_stds,
        "y_theta_only": y_theta_only,
        "y_uncal": y_uncal,
        "y_true": y_true,
        "y_meas": y_meas,
        "calibration": calibration,
        "em": em,
        "n_cal": n_cal,
        "x_cal": x_cal,
        "x_uncal": x_uncal,
        "x_true": vp.states,
    }
    return record, series, metrics


EXPERIMENTS = {"exp1": run_exp1, "exp2": run_exp2, "exp3": run_exp3}


def summarise(per_seed: list[dict], name: str) -> dict:
    """Mean and worst over seeds of the headline figures, with target checks."""
    summary = {}
    if name in ("exp1", "exp2"):
        for label in ("closed_loop_em",) + (
            ("closed_loop_ekf_only", "open_loop") if name == "exp1" else ()
        ):
            table = {}
            for minute in CHECK_MINUTES:
                key = f"{minute}min"
                for metric in per_seed[0][label][key]:
                    values = [m[label][key][metric] for m in per_seed]
                    table.setdefault(metric, {})[key] = {
                        "mean": float(np.mean(values)),
                        "worst": float(np.max(values)),
                    }
            summary[label] = table
        cov_key = "coverage_em"
        summary["coverage_em"] = {
            s: {
                "mean": float(np.mean([m[cov_key][s] for m in per_seed])),
                "worst_low": float(np.min([m[cov_key][s] for m in per_seed])),
                "worst_high": float(np.max([m[cov_key][s] for m in per_seed])),
            }
            for s in STATE_NAMES
        }
        worst_rel = max(
            summary["closed_loop_em"][STATE_NAMES[i] + "_rel_pct"][f"{mm}min"]["worst"]
            for i in RELATIVE_STATES
            for mm in CHECK_MINUTES
        )
        worst_nozzle = max(
            summary["closed_loop_em"]["nozzle_deposition_abs_nm"][f"{mm}min"]["worst"]
            for mm in CHECK_MINUTES
        )
        summary["targets"] = {
            "within_10pct_d_a_V_l_phi_A": worst_rel <= 10.0,
            "worst_relative_error_pct": worst_rel,
            "nozzle_within_5nm": worst_nozzle <= 5.0,
            "worst_nozzle_error_nm": worst_nozzle,
            "coverage_85_99_per_state": {
                s: 0.85 <= summary["coverage_em"][s]["mean"] <= 0.99 for s in STATE_NAMES
            },
        }
    if name == "exp3":
        targets = {}
        for output in ("linewidth", "overspray"):
            prefix = "" if output == "linewidth" else "overspray_"
            ratios = [m[f"{output}_rmse_ratio_calibrated_over_uncalibrated"] for m in per_seed]
            summary[f"{output}_rmse_ratio"] = {
                "mean": float(np.mean(ratios)),
                "worst": float(np.max(ratios)),
                "per_seed": [float(r) for r in ratios],
            }
            strict = [m[f"{output}_rmse_ratio_calibrated_over_theta_withheld"] for m in per_seed]
            summary[f"{output}_rmse_ratio_vs_theta_withheld_ablation"] = {
                "mean": float(np.mean(strict)),
                "worst": float(np.max(strict)),
                "per_seed": [float(r) for r in strict],
            }
            band = [m["forecast_band_coverage"][output] for m in per_seed]
            summary[f"{output}_forecast_band_coverage"] = {
                "mean": float(np.mean(band)),
                "worst_low": float(np.min(band)),
                "worst_high": float(np.max(band)),
            }
            targets[f"{prefix}calibrated_at_most_half_uncalibrated_all_seeds"] = bool(
                np.max(ratios) <= 0.5
            )
            targets[f"{prefix}calibrated_beats_theta_withheld_all_seeds"] = bool(
                np.max(strict) < 1.0
            )
            targets[f"{prefix}band_coverage_85_99_all_seeds"] = bool(
                min(band) >= 0.85 and max(band) <= 0.99
            )
        summary["targets"] = targets
    return summary


def run_experiment(
    name: str,
    seeds: list[int],
    out_dir: str | Path,
    twin_overrides=None,
    progress=None,
    truth: str = "model",
    figures=None,
) -> dict:
    """Run an experiment over seeds and write metrics.json (and figures of the first seed).

    ``truth="alt"`` runs exp3 on the second truth generator (evaluation only);
    ``figures(name, record, series, out_dir)`` draws the first seed's figures
    (:func:`ajtwin.studies.experiment_figures.experiment_figures`).
    """
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; choose one of {sorted(EXPERIMENTS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if truth != "model" and name != "exp3":
        raise ValueError(f"--truth {truth} is implemented for exp3 only, not {name}")
    per_seed = []
    for i, seed in enumerate(seeds):
        extra = {"truth": truth} if name == "exp3" else {}
        record, series, metrics = EXPERIMENTS[name](seed, twin_overrides, **extra)
        per_seed.append(metrics)
        if i == 0 and figures is not None:
            figures(name, record, series, out)
        if progress:
            progress(seed)
    result = {
        "experiment": name,
        "seeds": list(seeds),
        "truth_generator": truth,
        "twin_overrides": dict(twin_overrides or {}),
        "summary": summarise(per_seed, name),
        "per_seed": per_seed,
    }
    (out / "metrics.json").write_text(json.dumps(result, indent=2, default=float))
    return result
