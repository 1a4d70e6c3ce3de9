"""Exp 3 forecast skill of the transition profiles on both truth generators (issue 18).

Runs ``ajtwin experiment exp3`` for every profile of data/transition.toml named below on
the virtual printer's first truth generator ("model", which tuned the profiles on seeds
101–105) and on the second ("alt", evaluation only), held-out seeds 1–5, and optionally
exp1/exp2 (the filter's accuracy and coverage) for the profiles; writes each run's
figures and metrics.json under OUT/<experiment>_<profile>_<truth>/ and a summary table
OUT/summary.md with the before (paper) / after figures.

Run:  PYTHONPATH=src python benchmarks/bench_forecast.py --out docs/results/forecast
      [--profiles paper,input_following,mean_reverting] [--seeds 1-5] [--with-exp12]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ajtwin.estimation.experiments import run_experiment


def seeds_from(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def exp3_rows(profile: str, truth: str, result: dict) -> list[str]:
    per = result["per_seed"]

    def col(fn):
        return " ".join(f"{fn(m):.2f}" for m in per)

    f = "forecast_rmse_vs_noise_free_truth"
    ab = "ablation_same_start_state_without_theta_vs_noise_free_truth"
    s = result["summary"]
    lines = [
        f"| {profile} | {truth} | L_w | {col(lambda m: m[f]['linewidth_calibrated_um'])} "
        f"| {col(lambda m: m[f]['linewidth_uncalibrated_um'])} "
        f"| {col(lambda m: m[ab]['linewidth_um'])} "
        f"| {col(lambda m: m['linewidth_rmse_ratio_calibrated_over_uncalibrated'])} "
        f"(mean {s['linewidth_rmse_ratio']['mean']:.2f}) "
        f"| {col(lambda m: m['linewidth_rmse_ratio_calibrated_over_theta_withheld'])} "
        f"| {col(lambda m: m['forecast_band_coverage']['linewidth'])} "
        f"| {col(lambda m: m['oracle_droplet_forecast']['linewidth_um'])} |",
        f"| {profile} | {truth} | L_o | {col(lambda m: m[f]['overspray_calibrated_um'])} "
        f"| {col(lambda m: m[f]['overspray_uncalibrated_um'])} "
        f"| {col(lambda m: m[ab]['overspray_um'])} "
        f"| {col(lambda m: m['overspray_rmse_ratio_calibrated_over_uncalibrated'])} "
        f"(mean {s['overspray_rmse_ratio']['mean']:.2f}) "
        f"| {col(lambda m: m['overspray_rmse_ratio_calibrated_over_theta_withheld'])} "
        f"| {col(lambda m: m['forecast_band_coverage']['overspray'])} "
        f"| {col(lambda m: m['oracle_droplet_forecast']['overspray_um'])} |",
    ]
    return lines


def exp12_row(name: str, profile: str, result: dict) -> str:
    t = result["summary"]["targets"]
    cov = result["summary"]["coverage_em"]
    covs = " ".join(f"{cov[k]['mean']:.3f}" for k in cov)
    return (
        f"| {name} | {profile} | {t['worst_relative_error_pct']:.2f} | "
        f"{t['worst_nozzle_error_nm']:.2f} | {covs} |"
    )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", default=None, help="Result folder [default: a new temporary folder]."
    )
    parser.add_argument("--profiles", default="paper,input_following,mean_reverting")
    parser.add_argument("--truths", default="model,alt")
    parser.add_argument("--seeds", default="1-5")
    parser.add_argument("--with-exp12", action="store_true")
    args = parser.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_forecast-"))
    out.mkdir(parents=True, exist_ok=True)
    seeds = seeds_from(args.seeds)
    profiles = args.profiles.split(",")
    started = time.process_time()
    table = [
        "| profile | truth | output | calibrated RMSE µm (seeds) | uncalibrated | θ withheld "
        "| cal/uncal | cal/θ-withheld | ±2σ coverage | oracle-d_a RMSE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for profile in profiles:
        for truth in args.truths.split(","):
            target = out / f"exp3_{profile}_{truth}"
            overrides = {"noise_profile": "calibrated", "transition": profile}
            result = run_experiment("exp3", seeds, target, overrides, truth=truth)
            table += exp3_rows(profile, truth, result)
            print("\n".join(table[-2:]), flush=True)
    lines = [
        "# Exp 3 forecast skill by transition profile (benchmarks/bench_forecast.py)",
        "",
        f"Seeds {seeds}; profiles tuned on the first generator's training seeds 101–105 only.",
        "",
        *table,
    ]
    if args.with_exp12:
        lines += [
            "",
            "| experiment | profile | worst rel. error d_a/V_l/φ_A % | worst ΔR_N nm "
            "| ±2σ coverage d_a V_l ΔR_T ΔR_N φ_A |",
            "|---|---|---|---|---|",
        ]
        for name in ("exp1", "exp2"):
            for profile in profiles:
                target = out / f"{name}_{profile}"
                overrides = {"noise_profile": "calibrated", "transition": profile}
                result = run_experiment(name, seeds, target, overrides)
                lines.append(exp12_row(name, profile, result))
                print(lines[-1], flush=True)
    lines += [
        "",
        f"CPU time {time.process_time() - started:.0f} s; load {os.getloadavg()[0]:.1f}.",
    ]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps({"seeds": seeds, "profiles": profiles}))
    print(f"wrote {out / 'summary.md'}")
    return {
        "summary_md": str(out / "summary.md"),
        "experiments_cpu_s": round(time.process_time() - started, 1),
        "seeds": args.seeds,
        "profiles": args.profiles,
    }


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
    sys.exit(0)
