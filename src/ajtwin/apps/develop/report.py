"""A bring-up's report: the tests, the fitted ink, the window and the recipe, in a folder.

``tests.csv`` (one row a test line), ``fitted-ink.toml`` (the ink's values at the posterior
mean, with the equivalent line calibration of the machine: what ``ajtwin machine commission
--known`` can start from), ``window.png`` and ``report.md``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import tomli_w

from ajtwin.apps.develop.bringup import TEST_INPUTS, BringUp
from ajtwin.apps.develop.plot import window_figure
from ajtwin.apps.develop.prior import InkPrior, MachineLine

TEST_COLUMNS = (
    *TEST_INPUTS,
    "linewidth_um",
    "linewidth_std_um",
    "overspray_um",
    "overspray_std_um",
    "source",
)


def equivalent_calibration(bringup: BringUp, posterior) -> dict:
    """The ink's line as the nominal machine's line seen through a gain and an offset,
    L ≈ g L^nominal + o, least squares over the input box (for ``machine commission
    --known``), with the fit's rms [µm]."""
    nominal = InkPrior(bringup.settings, MachineLine())
    z = np.random.default_rng(0).random((512, bringup.box.dimension))
    inputs = bringup.box.inputs(z)
    pred = posterior.predict(inputs)
    ensemble = nominal.ensemble(inputs)
    out = {}
    for kind, name in ((0, "linewidth"), (1, "overspray")):
        fitted = np.array([pred.in_units(kind, i)[0] for i in range(len(inputs))])
        base = np.median((ensemble.linewidth, ensemble.overspray)[kind], axis=0)
        # the nominal machine's line: the prior's draw closest to the packaged numbers
        design = np.column_stack([base, np.ones_like(base)])
        (gain, offset), *_ = np.linalg.lstsq(design, fitted, rcond=None)
        rms = float(np.sqrt(np.mean((design @ [gain, offset] - fitted) ** 2)))
        out[name] = {"gain": float(gain), "offset_um": float(offset), "rms_um": rms}
    return out


def write_report(bringup: BringUp, out_dir) -> list[Path]:
    """Write the report's files into ``out_dir`` (created); returns their paths."""
    if not bringup.tests:
        raise ValueError("no test line yet: nothing to report")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    posterior = bringup.posterior()
    decision = bringup.decide(posterior)
    written = [out_dir / "tests.csv"]
    with open(written[0], "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(("test", *TEST_COLUMNS))
        for k, t in enumerate(bringup.tests, 1):
            writer.writerow((k, *(t.get(c, "") for c in TEST_COLUMNS)))
    ink = posterior.fitted_ink()
    calibration = equivalent_calibration(bringup, posterior)
    written.append(out_dir / "fitted-ink.toml")
    with open(written[-1], "wb") as fh:
        tomli_w.dump(
            {
                "format_version": 1,
                "goal": {k: float(v) for k, v in bringup.goal.__dict__.items()},
                "ink": ink,
                "equivalent_line_calibration": calibration,
                "residual_multipliers": {
                    "linewidth": posterior.multipliers[0],
                    "overspray": posterior.multipliers[1],
                },
                "note": "ink values at the posterior mean of the prior's ensemble (a "
                "linearisation); "
                "the residual multipliers > 1 say the line follows another law than the model's",
            },
            fh,
        )
    centre = _centre(bringup, decision)
    written.append(window_figure(bringup, posterior, centre, out_dir / "window.png"))
    written.append(out_dir / "report.md")
    written[-1].write_text(_markdown(bringup, decision, ink, calibration), encoding="utf-8")
    return written


def _centre(bringup, decision) -> list:
    for item in (decision.recipe, decision.closest, decision.test):
        if item:
            return [item[n] for n in TEST_INPUTS]
    return [bringup.tests[-1][n] for n in TEST_INPUTS]


def _markdown(bringup, decision, ink, calibration) -> str:
    g = bringup.goal
    lines = [
        "# Bring-up of a new ink",
        "",
        f"Goal: L_w {g.target_linewidth_um:g} ± {g.tolerance_um:g} µm, L_o ≤ "
        f"{g.max_overspray_um:g} µm, "
        f"P ≥ {g.probability:g}. Machine: {bringup.machine.name or 'nominal'}.",
        "",
        f"**{decision.kind.replace('_', ' ')}**: {decision.message}",
        "",
        "| test | I_A mA | Q_c sccm | Q_s sccm | ν mm/s | L_w µm | L_o µm |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, t in enumerate(bringup.tests, 1):
        lines.append(
            f"| {k} | {t['atomizer_current_mA']:g} | {t['carrier_flow_sccm']:g} | "
            f"{t['sheath_flow_sccm']:g} | "
            f"{t['speed_mm_s']:g} | {t['linewidth_um']:.2f} ± {t['linewidth_std_um']:.2f} | "
            f"{t['overspray_um']:.2f} ± {t['overspray_std_um']:.2f} |"
        )
    if decision.recipe:
        r = decision.recipe
        lines += [
            "",
            f"Recipe: I_A {r['atomizer_current_mA']:g} mA, Q_c {r['carrier_flow_sccm']:g} sccm, "
            f"Q_s {r['sheath_flow_sccm']:g} sccm, ν {r['speed_mm_s']:g} mm/s: L_w "
            f"{r['linewidth_um']:.1f} ± "
            f"{r['linewidth_2sd_um']:.1f} µm, L_o {r['overspray_um']:.1f} ± "
            f"{r['overspray_2sd_um']:.1f} µm (2σ).",
        ]
    lines += ["", "Fitted ink (posterior mean):", ""]
    lines += [f"- {k}: {v:.3g}" for k, v in ink.items()]
    w, o = calibration["linewidth"], calibration["overspray"]
    lines += [
        "",
        "Commissioning the machine with this ink can start from its line:",
        "",
        "```",
        f"ajtwin machine commission NAME RECORD --known linewidth_gain={w['gain']:.3f}±0.1 "
        f"--known linewidth_offset_um={w['offset_um']:.1f}±{max(3 * w['rms_um'], 2.0):.1f} "
        f"--known overspray_gain={o['gain']:.3f}±0.2 --known "
        f"overspray_offset_um={o['offset_um']:.1f}±"
        f"{max(3 * o['rms_um'], 1.0):.1f}",
        "```",
        "",
        "![window](window.png)",
        "",
    ]
    return "\n".join(lines)
