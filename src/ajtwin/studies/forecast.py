"""Exp 3 forecast skill of the transition variants on both truth generators.

Runs ``ajtwin experiment exp3`` for every variant of data/transition.toml named below on
the virtual printer's first truth generator ("model", which tuned the variants on seeds
101–105) and on the second ("alt", evaluation only), held-out seeds 1–5, and optionally
exp1/exp2 (the filter's accuracy and coverage) for the variants; writes each run's
figures and metrics.json under OUT/<experiment>_<variant>_<truth>/ and a summary table
OUT/summary.md with the before (paper) / after figures.

Run::

    python -m ajtwin.studies.forecast --out docs/results/forecast \
        [--variants paper,input_following,mean_reverting] [--seeds 1-5] [--with-exp12]
    python -m ajtwin.studies.forecast --out docs/results/forecast/seeds_1_40 \
        --variants paper,input_following --seeds 1-40   # the pooled bands (summary.md, top table)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ajtwin.studies import machine_description
from ajtwin.studies.experiments import run_experiment


def seeds_from(text: str) -> list[int]:
    """Seeds from ``1-5`` or ``1,3,7``."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def exp3_rows(variant: str, truth: str, result: dict) -> list[str]:
    """Table rows of one droplet-row variant and truth generator over the exp3 seeds."""
    per = result["per_seed"]

    def col(fn):
        return " ".join(f"{fn(m):.2f}" for m in per)

    f = "forecast_rmse_vs_noise_free_truth"
    ab = "ablation_same_start_state_without_theta_vs_noise_free_truth"
    s = result["summary"]
    lines = [
        f"| {variant} | {truth} | L_w | {col(lambda m: m[f]['linewidth_calibrated_um'])} "
        f"| {col(lambda m: m[f]['linewidth_uncalibrated_um'])} "
        f"| {col(lambda m: m[ab]['linewidth_um'])} "
        f"| {col(lambda m: m['linewidth_rmse_ratio_calibrated_over_uncalibrated'])} "
        f"(mean {s['linewidth_rmse_ratio']['mean']:.2f}) "
        f"| {col(lambda m: m['linewidth_rmse_ratio_calibrated_over_theta_withheld'])} "
        f"| {col(lambda m: m['forecast_band_coverage']['linewidth'])} "
        f"| {col(lambda m: m['oracle_droplet_forecast']['linewidth_um'])} |",
        f"| {variant} | {truth} | L_o | {col(lambda m: m[f]['overspray_calibrated_um'])} "
        f"| {col(lambda m: m[f]['overspray_uncalibrated_um'])} "
        f"| {col(lambda m: m[ab]['overspray_um'])} "
        f"| {col(lambda m: m['overspray_rmse_ratio_calibrated_over_uncalibrated'])} "
        f"(mean {s['overspray_rmse_ratio']['mean']:.2f}) "
        f"| {col(lambda m: m['overspray_rmse_ratio_calibrated_over_theta_withheld'])} "
        f"| {col(lambda m: m['forecast_band_coverage']['overspray'])} "
        f"| {col(lambda m: m['oracle_droplet_forecast']['overspray_um'])} |",
    ]
    return lines


def pooled_row(variant: str, truth: str, result: dict) -> str:
    """One line over all seeds: a seed's band is all or nothing when its error is
    systematic, so the band's honesty is judged pooled (85–99 %), not seed by seed."""
    per = result["per_seed"]
    band_w = np.array([m["forecast_band_coverage"]["linewidth"] for m in per])
    band_o = np.array([m["forecast_band_coverage"]["overspray"] for m in per])
    f = "forecast_rmse_vs_noise_free_truth"
    cal = np.array([m[f]["linewidth_calibrated_um"] for m in per])
    uncal = np.array([m[f]["linewidth_uncalibrated_um"] for m in per])
    ratio = np.array([m["linewidth_rmse_ratio_calibrated_over_uncalibrated"] for m in per])
    withheld = np.array([m["linewidth_rmse_ratio_calibrated_over_theta_withheld"] for m in per])
    return (
        f"| {variant} | {truth} | {len(per)} | {band_w.mean():.3f} ({(band_w < 0.85).sum()}) "
        f"| {band_o.mean():.3f} ({(band_o < 0.85).sum()}) "
        f"| {np.sqrt(np.mean(cal**2) / np.mean(uncal**2)):.2f} ({(ratio <= 0.5).sum()}) "
        f"| {np.median(withheld):.3f} ({(withheld < 1).sum()}) |"
    )


def exp12_row(name: str, variant: str, result: dict) -> str:
    """A table row of exp1/exp2 under one droplet-row variant: worst errors and ±2σ coverage."""
    t = result["summary"]["targets"]
    cov = result["summary"]["coverage_em"]
    covs = " ".join(f"{cov[k]['mean']:.3f}" for k in cov)
    return (
        f"| {name} | {variant} | {t['worst_relative_error_pct']:.2f} | "
        f"{t['worst_nozzle_error_nm']:.2f} | {covs} |"
    )


def main(argv=None) -> dict:
    """Run the forecast study (exp3 per droplet-row variant and truth, optionally exp1/exp2); its
    figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", default=None, help="Result folder [default: a new temporary folder]."
    )
    parser.add_argument(
        "--variants", "--variants", dest="variants", default="paper,input_following,mean_reverting"
    )
    parser.add_argument("--truths", default="model,alt")
    parser.add_argument("--seeds", default="1-5")
    parser.add_argument("--with-exp12", action="store_true")
    args = parser.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ajtwin-forecast-study-"))
    out.mkdir(parents=True, exist_ok=True)
    seeds = seeds_from(args.seeds)
    variants = args.variants.split(",")
    started = time.process_time()
    table = [
        "| variant | truth | output | calibrated RMSE µm (seeds) | uncalibrated | θ withheld "
        "| cal/uncal | cal/θ-withheld | ±2σ coverage | oracle-d_a RMSE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    pooled = [
        "| variant | truth | seeds | L_w ±2σ coverage, pooled (seeds < 85 %) | L_o (seeds < 85 %) "
        "| L_w RMSE cal/uncal, pooled (seeds ≤ 0.5) | cal/θ-withheld, median (seeds < 1) |",
        "|---|---|---|---|---|---|---|",
    ]
    for variant in variants:
        for truth in args.truths.split(","):
            target = out / f"exp3_{variant}_{truth}"
            overrides = {"noise_tuning": "calibrated", "transition": variant}
            result = run_experiment("exp3", seeds, target, overrides, truth=truth)
            table += exp3_rows(variant, truth, result)
            pooled.append(pooled_row(variant, truth, result))
            print("\n".join(table[-2:]), flush=True)
    lines = [
        "# Exp 3 forecast skill by transition variant (python -m ajtwin.studies.forecast)",
        "",
        f"Seeds {seeds[0]}–{seeds[-1]} (held out); the variants were tuned on the first "
        "generator's training seeds (101–105; input_following's forecast σ_da on 101–140).",
        "",
        *pooled,
        "",
        *table,
    ]
    if args.with_exp12:
        lines += [
            "",
            "| experiment | variant | worst rel. error d_a/V_l/φ_A % | worst ΔR_N nm "
            "| ±2σ coverage d_a V_l ΔR_T ΔR_N φ_A |",
            "|---|---|---|---|---|",
        ]
        for name in ("exp1", "exp2"):
            for variant in variants:
                target = out / f"{name}_{variant}"
                overrides = {"noise_tuning": "calibrated", "transition": variant}
                result = run_experiment(name, seeds, target, overrides)
                lines.append(exp12_row(name, variant, result))
                print(lines[-1], flush=True)
    lines += [
        "",
        f"CPU time {time.process_time() - started:.0f} s on {machine_description()}.",
    ]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps({"seeds": seeds, "variants": variants}))
    print(f"wrote {out / 'summary.md'}")
    return {
        "summary_md": str(out / "summary.md"),
        "experiments_cpu_s": round(time.process_time() - started, 1),
        "seeds": args.seeds,
        "variants": args.variants,
    }


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
    sys.exit(0)
