"""The twin on machines it was not built from: held-out virtual machines, commissioned.

Held-out virtual machines (machine seeds 1001–1005, print seeds 2001+) on the SECOND
truth generator (``truth_generator="alt"``, which tuned nothing), plus the nominal
machine and the paper's machine. Per machine:

1. a 20-min ``commissioning`` print → :func:`ajtwin.estimation.commission.commission`
   (d_a known from a droplet measurement: truth + N(0, 0.1 µm), given as ±0.1 µm);
2. the next 90-min ``exp1`` print of that machine (continuing from the commissioning
   print) run by the calibrated twin, started where commissioning left the machine:
   errors at 30/60/90 min, ±2σ coverage, alarms, the mismatch guard; the detectors start
   with the long-run noise scale the calibrated twin showed on the commissioning print
   (:func:`ajtwin.engine.commissioning.commissioning_long_run_history`, as the registry carries it);
3. BEFORE: the same print run by the uncalibrated (nominal) twin, as a new user would:
   errors, coverage, alarms, when the guard fires;
4. a 30-min ``nozzle_clog`` print (onset 15 min) on the commissioned machine:
   detection delay and label.

``--atomizer-variant``: the same machines with an atomizer that is not the generation
model (0.7–1.3 × H, drifting up to ±12 % per hour;
:func:`ajtwin.simulation.truth_alt.off_model_atomizer_machine`), to judge φ_A's band when
nothing pins its level; ``--pin gain`` adds a profilometer-calibrated CNN's gain (truth +
N(0, 3 %), declared ±3 %), ``--pin vial`` the vial weighed before and after the
commissioning print (ink used: truth + N(0, 0.01 µL), declared ±0.01 µL — a 0.01-mg balance
on a silver ink of ~2 g/mL, an assumption).

``python -m ajtwin.studies.machine [--quick]`` writes
``docs/results/machine/results.json`` and ``summary.md``; ``main()`` without arguments
runs the quick version (one machine, shorter prints).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ajtwin.apps.detection.batch import detect_run
from ajtwin.apps.detection.mismatch import assess_run, relabel_events
from ajtwin.engine.commissioning import (
    calibrated_twin,
    commission_machine,
    commissioned_start,
    commissioning_long_run_history,
)
from ajtwin.estimation.twin import Twin
from ajtwin.simulation.printer import run_virtual_print
from ajtwin.simulation.truth_alt import off_model_atomizer_machine
from ajtwin.studies import machine_description

#: where the full run writes (relative to the working directory: the repository's root)
OUT = Path("docs") / "results" / "machine"
MACHINE_SEEDS = (1001, 1002, 1003, 1004, 1005)
CHECK_MIN = (30, 60, 90)
STATES = ("d_a", "V_l", "ΔR_T", "ΔR_N", "φ_A")
#: d_a measured at commissioning (a droplet sizer): its error, drawn and declared alike
DROPLET_SIZER_STD_UM = 0.1
#: ``--pin gain``: a CNN calibrated against a profilometer, relative error of its Q_m gain
GAIN_PIN_RELATIVE_STD = 0.03
#: ``--pin vial``: the ink used, weighed before and after the commissioning print [mL]
VIAL_USED_STD_ML = 1e-5
PINS = ("none", "gain", "vial")


def _errors(run, states, minutes):
    out = {}
    for m in minutes:
        k = min(int(m * 60) - 1, len(states) - 1)
        est, truth = run.means[k], states[k]
        out[f"{m}min"] = {
            "d_a_rel": float(abs(est[0] - truth[0]) / truth[0]),
            "V_l_rel": float(abs(est[1] - truth[1]) / truth[1]),
            "phi_A_rel": float(abs(est[4] - truth[4]) / truth[4]),
            "dRN_nm": float(abs(est[3] - truth[3]) * 1e3),
        }
    return out


def _coverage(run, states):
    z = np.abs(run.means - states) / np.maximum(run.stds, 1e-300)
    return {name: float(np.mean(z[:, i] <= 2.0)) for i, name in enumerate(STATES)}


def _square_z(run, states):
    """Σ z² and count per state, z = (x̂ − x)/σ (pooled into an rms z by summarise)."""
    z = (run.means - states) / np.maximum(run.stds, 1e-300)
    return {name: [float(np.sum(z[:, i] ** 2)), int(len(z))] for i, name in enumerate(STATES)}


def _run(twin, record, start=None, long_run_history=None):

    t0 = time.process_time()
    run = twin.run(record, start=start)
    status = assess_run(run, record)
    detection = detect_run(run, record, long_run_history=long_run_history)
    events = relabel_events(detection.events, status)
    return run, status, events, time.process_time() - t0


def print_seed_of(machine_seed: int) -> int:
    """The first print seed of a held-out machine: its prints follow its machine seed."""
    return 2001 + 10 * (machine_seed - MACHINE_SEEDS[0])


def level_pins(comm, pin: str, rng) -> dict:
    """The ``commission_machine`` keywords of a pin of φ_A's level, drawn with a lab's error
    from the commissioning print's truth: ``gain`` (a profilometer-calibrated CNN), ``vial``
    (the ink used, weighed), ``none``."""
    if pin == "gain":
        true_gain = comm.machine.calibration().material_flow_gain
        known = true_gain * (1.0 + GAIN_PIN_RELATIVE_STD * rng.standard_normal())
        return {"known": {"material_flow_gain": (known, GAIN_PIN_RELATIVE_STD * known)}}
    if pin == "vial":
        used = float(comm.states[0, 1] - comm.states[-1, 1])
        weighed = used + VIAL_USED_STD_ML * rng.standard_normal()
        return {"vial_used_ml": (weighed, VIAL_USED_STD_ML)}
    if pin != "none":
        raise ValueError(f"pin {pin!r}: choose one of {', '.join(PINS)}")
    return {}


def commission_virtual_machine(
    print_seed, truth="alt", machine=None, machine_seed=None, learn_noise_scale=True, pin="none"
):
    """A virtual machine's 20-min commissioning print, commissioned as ``ajtwin machine
    commission`` does (:func:`ajtwin.engine.commissioning.commission_machine`).

    d_a is known from a droplet sizer: truth + N(0, 0.1 µm), declared ±0.1 µm.
    ``learn_noise_scale``: also the detectors' long-run statistics (not timed).
    ``pin``: what pins φ_A's level (:func:`level_pins`).
    Returns (commissioning print, Commissioning, CPU seconds of the fit).
    """
    rng = np.random.default_rng(print_seed)
    comm = run_virtual_print(
        "commissioning",
        seed=print_seed,
        machine=machine,
        machine_seed=machine_seed,
        truth_generator=truth,
    )
    measured_da = float(comm.states[0, 0] + DROPLET_SIZER_STD_UM * rng.standard_normal())
    known = {"droplet_diameter_um": (measured_da, DROPLET_SIZER_STD_UM)}
    pinned = level_pins(comm, pin, rng)
    known.update(pinned.pop("known", {}))
    t0 = time.process_time()
    done = commission_machine(comm.record, known=known, learn_noise_scale=False, **pinned)
    cpu = time.process_time() - t0
    if learn_noise_scale:
        # the detectors' long-run noise scale of this machine, as `machine commission` stores it
        done.long_run_history = commissioning_long_run_history(comm.record, done.result)
    return comm, done, cpu


def evaluate_machine(
    machine_seed=None,
    machine=None,
    print_seed=2001,
    minutes=90.0,
    clog=True,
    truth="alt",
    atomizer_variant=False,
    pin="none",
):
    """One virtual machine: commission it, then its next print by the calibrated and by the
    nominal twin (errors, coverage, alarms, the guard) and a clog (delay, label).

    Parameters
    ----------
    machine_seed : int, optional
        A drawn held-out machine; or ``machine`` by name (``paper``).
    print_seed : int
    minutes : float
        Length of the clean print [min].
    clog : bool
        Also the clogging print.
    truth : str
        ``alt`` (evaluation) or ``model``.
    atomizer_variant : bool
        The machine's atomizer is not the generation model (``machine_seed`` draws it).
    pin : str
        What pins φ_A's level at commissioning (:data:`PINS`).
    """
    if atomizer_variant:
        machine, machine_seed = off_model_atomizer_machine(machine_seed), None
    comm, done, commission_cpu = commission_virtual_machine(
        print_seed, truth, machine, machine_seed, pin=pin
    )
    result, history = done.result, done.long_run_history
    truth_cal = comm.machine.calibration()._asdict()
    recovery = {
        row["parameter"]: {
            "true": truth_cal[row["parameter"]],
            "fitted": row["value"],
            "std_error": row["std_error"],
            "z": (row["value"] - truth_cal[row["parameter"]]) / row["std_error"],
            "determined": row["determined"],
        }
        for row in result.table()
    }
    nxt = run_virtual_print(
        "exp1",
        seed=print_seed + 1,
        duration_min=minutes,
        continue_from=comm.record,
        truth_generator=truth,
    )
    start = commissioned_start(result)
    checks = [m for m in CHECK_MIN if m <= minutes]
    after_run, after_status, after_events, after_cpu = _run(
        calibrated_twin(result),
        nxt.record,
        start,
        history,
    )
    before_run, before_status, before_events, before_cpu = _run(Twin.default(), nxt.record)
    out = {
        "machine": comm.machine.name,
        "deviation": comm.machine.as_dict()["equivalent_calibration"],
        "atomizer_output": comm.machine.atomizer_output,
        "aerosol_level": getattr(result, "aerosol_level", {}),
        "commission_cpu_s": commission_cpu,
        "calibration_recovery": recovery,
        "after": {
            "errors": _errors(after_run, nxt.states, checks),
            "coverage": _coverage(after_run, nxt.states),
            "square_z": _square_z(after_run, nxt.states),
            "alarms": [(e.cause, e.detected_s) for e in after_events],
            "mismatch": after_status.to_dict(),
            "cpu_s": after_cpu,
        },
        "before": {
            "errors": _errors(before_run, nxt.states, checks),
            "coverage": _coverage(before_run, nxt.states),
            "alarms": [(e.cause, e.detected_s) for e in before_events],
            "mismatch": before_status.to_dict(),
            "cpu_s": before_cpu,
        },
        "print_hours": minutes / 60.0,
    }
    if clog:
        clog_min = min(30.0, minutes)
        clog_print = run_virtual_print(
            "nozzle_clog",
            seed=print_seed + 2,
            duration_min=clog_min,
            continue_from=comm.record,
            overrides={"fault": {"onset_min": clog_min / 2}},
            truth_generator=truth,
        )
        _, clog_status, clog_events, _ = _run(
            calibrated_twin(result),
            clog_print.record,
            start,
            history,
        )
        onset = clog_print.record.meta["fault_onset_s"]
        hits = [e for e in clog_events if e.cause == "nozzle_clog" and e.detected_s >= onset]
        out["clog"] = {
            "onset_s": onset,
            "delay_s": None if not hits else hits[0].detected_s - onset,
            "events": [(e.cause, e.onset_s, e.detected_s) for e in clog_events],
            "mismatch": clog_status.mismatch,
        }
    return out


def evaluate_nominal(print_seed=2101, minutes=90.0):
    """The nominal machine, never commissioned: the guard must stay silent."""

    out = {}
    for generator in ("alt", "model"):
        vp = run_virtual_print(
            "exp1", seed=print_seed, duration_min=minutes, truth_generator=generator
        )
        run, status, events, cpu = _run(Twin.default(), vp.record)
        out[generator] = {
            "errors": _errors(run, vp.states, [m for m in CHECK_MIN if m <= minutes]),
            "coverage": _coverage(run, vp.states),
            "alarms": [(e.cause, e.detected_s) for e in events],
            "mismatch": status.to_dict(),
            "cpu_s": cpu,
            "print_hours": minutes / 60.0,
        }
    return out


def summarise(results: dict) -> dict:
    """Worst errors, coverage ranges, false alarms per 10 h, clog delays, the guard and rms z over
    the machines."""
    machines = results["machines"]
    worst = {}
    for phase in ("after", "before"):
        errs = [m[phase]["errors"][k] for m in machines for k in m[phase]["errors"]]
        worst[phase] = {
            key: max(e[key] for e in errs) for key in ("d_a_rel", "V_l_rel", "phi_A_rel", "dRN_nm")
        }
        cov = [m[phase]["coverage"] for m in machines]
        worst[phase]["coverage_min"] = {s: min(c[s] for c in cov) for s in STATES}
        worst[phase]["coverage_max"] = {s: max(c[s] for c in cov) for s in STATES}
    hours = sum(m["print_hours"] for m in machines)
    clean_alarms = sum(
        len([a for a in m["after"]["alarms"] if a[0] != "model_machine_mismatch"]) for m in machines
    )
    nominal = results["nominal"]
    hours += sum(v["print_hours"] for v in nominal.values())
    clean_alarms += sum(len(v["alarms"]) for v in nominal.values())
    summary = {
        "worst": worst,
        "false_alarms_per_10h_clean": 10.0 * clean_alarms / hours,
        "clean_print_hours": hours,
        "coverage_pooled_after": {
            st: float(np.mean([m["after"]["coverage"][st] for m in machines])) for st in STATES
        },
        "machines_below_85_after": {
            st: int(sum(m["after"]["coverage"][st] < 0.85 for m in machines)) for st in STATES
        },
        "clog_delay_s": [m.get("clog", {}).get("delay_s") for m in machines],
        "guard_uncommissioned_first_s": [m["before"]["mismatch"]["first_s"] for m in machines],
        "guard_commissioned_fired": [m["after"]["mismatch"]["mismatch"] for m in machines],
        "guard_nominal_fired": {g: v["mismatch"]["mismatch"] for g, v in nominal.items()},
        # honest bands: 1; below 1 the bands are too wide (pooled over the machines, after)
        "rms_z_after": {
            s: float(
                np.sqrt(
                    sum(m["after"]["square_z"][s][0] for m in machines)
                    / sum(m["after"]["square_z"][s][1] for m in machines)
                )
            )
            for s in STATES
        },
    }
    if "paper" in results:
        summary["paper_after_errors"] = results["paper"]["after"]["errors"]
        summary["paper_before_errors"] = results["paper"]["before"]["errors"]
    return summary


def run_all(
    quick: bool = False,
    progress=print,
    n_machines=None,
    checkpoint=None,
    seeds=None,
    truth="alt",
    atomizer_variant=False,
    pin="none",
) -> dict:
    """``seeds``: other held-out machine seeds (``--seeds 1006-1020``; print seeds follow
    the machine seed, so 1001-1005 print exactly as in the default run). ``truth``: the
    generator of the varied machines' prints — "alt" (evaluation, the default) or "model"
    (the first generator, on which the twin's priors may be tuned). ``atomizer_variant``
    and ``pin``: see the module docstring."""
    if seeds is None:
        seeds = MACHINE_SEEDS[:1] if quick else MACHINE_SEEDS[: n_machines or len(MACHINE_SEEDS)]
    minutes = 30.0 if quick else 90.0
    results = {"machines": []}
    t0 = time.perf_counter()
    # the nominal and the paper's machine first: a stopped run still has them
    results["nominal"] = evaluate_nominal(minutes=minutes)
    progress(f"nominal done ({time.perf_counter() - t0:.0f} s)")
    results["truth"] = truth
    results["atomizer_variant"] = bool(atomizer_variant)
    results["pin"] = pin
    results["paper"] = evaluate_machine(
        machine="paper", print_seed=2201, minutes=minutes, clog=False, truth=truth, pin=pin
    )
    progress(f"paper done ({time.perf_counter() - t0:.0f} s)")
    for seed in seeds:
        results["machines"].append(
            evaluate_machine(
                machine_seed=seed,
                print_seed=print_seed_of(seed),
                minutes=minutes,
                truth=truth,
                atomizer_variant=atomizer_variant,
                pin=pin,
            )
        )
        progress(f"machine {seed} done ({time.perf_counter() - t0:.0f} s)")
        if checkpoint is not None:  # nothing lost if the run is stopped
            checkpoint(results)
    results["summary"] = summarise(results)
    results["wall_s"] = time.perf_counter() - t0
    return results


def _markdown(results: dict, command: str, computer: str) -> str:
    s = results["summary"]
    lines = [
        "# The twin on machines it was not built from",
        "",
        f"Command: `{command}`  ",
        f"Computer: {computer}; wall {results['wall_s']:.0f} s.",
        (
            "Evaluation on the SECOND truth generator (`--truth alt`, tuned nothing); machines "
            if results.get("truth", "alt") == "alt"
            else "On the FIRST truth generator (`--truth model`, the twin's own equations: "
            "where priors may be tuned, not evaluated); machines "
        )
        + f"{', '.join(m['machine'] for m in results['machines'])}, print seeds 2001+.",
        "",
        "| machine | phase | d_a err 30/60/90 | φ_A err 30/60/90 | V_l err 30/60/90 "
        "| ΔR_N nm 30/60/90 | cover d_a/V_l/φ_A/ΔR_N/ΔR_T | alarms | guard |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def row(name, phase, r):
        e = r["errors"]
        f = lambda key, scale=100.0: "/".join(f"{e[k][key] * scale:.1f}" for k in e)  # noqa: E731
        c = r["coverage"]
        cover = "/".join(f"{c[k] * 100:.0f}" for k in ("d_a", "V_l", "φ_A", "ΔR_N", "ΔR_T"))
        guard = r["mismatch"]
        g = f"fires {guard['first_s']:.0f} s" if guard["mismatch"] else "silent"
        return (
            f"| {name} | {phase} | {f('d_a_rel')} % | {f('phi_A_rel')} % | {f('V_l_rel')} % | "
            f"{f('dRN_nm', 1.0)} | {cover} % | {len(r['alarms'])} | {g} |"
        )

    for m in results["machines"]:
        lines.append(row(m["machine"], "after", m["after"]))
        lines.append(row(m["machine"], "before", m["before"]))
    for gen, r in results["nominal"].items():
        lines.append(row(f"nominal ({gen} truth)", "uncommissioned", r))
    if "paper" in results:
        lines.append(row("paper", "after", results["paper"]["after"]))
        lines.append(row("paper", "before", results["paper"]["before"]))
    lines += [
        "",
        f"False alarms on clean prints (alt truth, commissioned machines + nominal): "
        f"{s['false_alarms_per_10h_clean']:.2f} per 10 print-hours over "
        f"{s['clean_print_hours']:.1f} h.",
        f"Clog detection delay after onset on commissioned machines [s]: {s['clog_delay_s']}.",
        "Guard on uncommissioned machines, first finding [s]: "
        f"{s['guard_uncommissioned_first_s']}.",
        f"Guard on commissioned machines fired: {s['guard_commissioned_fired']}; "
        f"on the nominal machine: {s['guard_nominal_fired']}.",
        "rms z = (estimate − truth)/σ pooled over the commissioned machines (1 = honest "
        "bands): " + ", ".join(f"{k} {v:.2f}" for k, v in s["rms_z_after"].items()) + ".",
        "±2σ coverage pooled over the commissioned machines: "
        + ", ".join(f"{k} {v * 100:.1f} %" for k, v in s["coverage_pooled_after"].items())
        + "; machines below 85 %: "
        + ", ".join(f"{k} {v}" for k, v in s["machines_below_85_after"].items())
        + ".",
        "",
    ]
    if results.get("atomizer_variant"):
        lines += _atomizer_lines(results), ""
    lines += ["Calibration recovery (z = (fitted − true)/std error, determined parameters):", ""]
    for m in results["machines"] + ([results["paper"]] if "paper" in results else []):
        zs = {k: v["z"] for k, v in m["calibration_recovery"].items() if v["determined"]}
        worst = max(zs, key=lambda k: abs(zs[k]))
        lines.append(
            f"- {m['machine']}: max |z| {abs(zs[worst]):.2f} ({worst}); not determined: "
            f"{[k for k, v in m['calibration_recovery'].items() if not v['determined']]}"
        )
    return "\n".join(lines) + "\n"


def _atomizer_lines(results: dict) -> str:
    """Per machine of the atomizer variant: its atomizer's output, φ_A's level as
    commissioning found it, the Q_m gain's recovery, φ_A's coverage and worst error."""
    rows = [
        f"Atomizer not the generation model (pin: {results.get('pin', 'none')}):",
        "",
        "| machine | atomizer / H | level found | Q_m gain true / fitted (z) | φ_A cover | "
        "φ_A worst err |",
        "|---|---|---|---|---|---|",
    ]
    for m in results["machines"]:
        level = m.get("aerosol_level") or {}
        gain = m["calibration_recovery"]["material_flow_gain"]
        found = (
            f"{level['relative']:.3f} ± {level['relative_std']:.3f}" if level else "–"
        )  # fmt: skip
        worst = max(e["phi_A_rel"] for e in m["after"]["errors"].values())
        rows.append(
            f"| {m['machine']} | {m['atomizer_output']:.3f} | {found} | {gain['true']:.3f} / "
            f"{gain['fitted']:.3f} ({gain['z']:+.1f}) | {m['after']['coverage']['φ_A'] * 100:.0f} "
            f"% | {worst * 100:.1f} % |"
        )
    return "\n".join(rows)


def main() -> dict:
    """The quick version: one machine, 30-min prints."""
    results = run_all(quick=True, progress=lambda _: None)
    s = results["summary"]
    return {
        "quick_after_worst_d_a_rel": s["worst"]["after"]["d_a_rel"],
        "quick_after_worst_phi_A_rel": s["worst"]["after"]["phi_A_rel"],
        "quick_false_alarms_per_10h": s["false_alarms_per_10h_clean"],
        "quick_wall_s": results["wall_s"],
    }


if __name__ == "__main__":
    quick = "--quick" in sys.argv
    n_machines = None
    if "--machines" in sys.argv:
        n_machines = int(sys.argv[sys.argv.index("--machines") + 1])
    seeds = None
    if "--seeds" in sys.argv:  # e.g. 1006-1020: more held-out machines, results_1006_1020.*
        first, last = (int(v) for v in sys.argv[sys.argv.index("--seeds") + 1].split("-"))
        seeds = list(range(first, last + 1))
    truth = "alt"
    if "--truth" in sys.argv:  # model: the first generator (tuning), alt: evaluation
        truth = sys.argv[sys.argv.index("--truth") + 1]
        if truth not in ("alt", "model"):
            sys.exit(f"--truth {truth!r}: choose alt or model")
    atomizer_variant = "--atomizer-variant" in sys.argv
    if atomizer_variant and truth != "alt":
        sys.exit("--atomizer-variant is a variant of the second generator: use --truth alt")
    pin = "none"
    if "--pin" in sys.argv:  # what pins φ_A's level at commissioning
        pin = sys.argv[sys.argv.index("--pin") + 1]
        if pin not in PINS:
            sys.exit(f"--pin {pin!r}: choose one of {', '.join(PINS)}")
    OUT.mkdir(parents=True, exist_ok=True)
    name = "quick" if quick else "results" if seeds is None else f"results_{first}_{last}"
    if truth != "alt":
        name += f"_{truth}"
    if atomizer_variant:
        name += "_atomizer"
    if pin != "none":
        name += f"_pin_{pin}"

    def checkpoint(partial):
        (OUT / f"{name}.partial.json").write_text(json.dumps(partial, indent=1, default=float))

    results = run_all(
        quick=quick,
        n_machines=n_machines,
        checkpoint=checkpoint,
        seeds=seeds,
        truth=truth,
        atomizer_variant=atomizer_variant,
        pin=pin,
    )
    (OUT / f"{name}.json").write_text(json.dumps(results, indent=1, default=float))
    (OUT / f"{name}.partial.json").unlink(missing_ok=True)  # the whole run is in name.json
    command = "python -m ajtwin.studies.machine" + (" --quick" if quick else "")
    if n_machines:
        command += f" --machines {n_machines}"
    if seeds:
        command += f" --seeds {first}-{last}"
    if truth != "alt":
        command += f" --truth {truth}"
    if atomizer_variant:
        command += " --atomizer-variant"
    if pin != "none":
        command += f" --pin {pin}"
    (OUT / f"{name}.md").write_text(_markdown(results, command, machine_description()))
    print(_markdown(results, command, machine_description()))
