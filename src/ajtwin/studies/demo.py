"""The demo: the twin in use, end to end, on a virtual machine with a fault (``ajtwin demo``).

1. The virtual printer prints twice on one machine: a clean 15-min print, then a
   40-min print (continuing from the first: vial level and deposits carry over) in which
   the nozzle starts to clog at 20 min (``nozzle_clog``, onset moved earlier to keep the
   demo short).
2. The second print's alignment-camera video is rendered (``ajtwin.vision``, one frame
   every 10 s) and linewidth/overspray are extracted from it back into the record; the
   twin sees only the video's values for L_w and L_o. Q_m comes from the record (the
   virtual printer's CNN-like measurement: training the profile CNN does not fit into the
   demo's time budget).
3. A machine registry (``demo-output/registry.sqlite``) gets the machine and both prints:
   the second starts from the first's end state and θ.
4. The anomaly detectors run on the twin's innovations; the alarm, its likely cause and
   its delay against the true onset are reported.
5. A forecast (carry on printing, and Q_c → 26 sccm) with ±2σ bands, and input advice
   for a 43 µm line.
6. ``demo-output/report.html`` (one self-contained page) and a terminal summary.

Each step is a function of this module; :func:`run_demo` runs them in order.
"""

from __future__ import annotations

import html
import time
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from ajtwin import units
from ajtwin.apps.detection.causes import alarm_sentence, detector_words, open_faults
from ajtwin.apps.planning.advice import advise
from ajtwin.apps.planning.forecast import forecast, input_schedule, parse_change
from ajtwin.engine.ingest import ingest_record
from ajtwin.engine.start import apply_maintenance
from ajtwin.engine.video import join_video
from ajtwin.estimation import Twin
from ajtwin.estimation.commission import aerosol_level_note
from ajtwin.io.records import write_record
from ajtwin.simulation import simulate
from ajtwin.store.registry import Registry
from ajtwin.studies import demo_report as report
from ajtwin.vision.record_render import render_record_video
from ajtwin.vision.render import RenderSettings, TruthFile

CLEAN_MIN = 15.0
FAULT_MIN = 40.0
FAULT_ONSET_MIN = 20.0
VIDEO_FPS = 0.1
VIDEO_SHAPE = (400, 640)  # rows, columns [px]
UM_PER_PX = 0.75
MACHINE = "demo-aj300"
#: the linewidth the demo asks advice for [µm], and its overspray limit [µm]
TARGET_UM = 43.0
MAX_OVERSPRAY_UM = 35.0
#: forecast horizon [s]
HORIZON_S = 900


class Stages:
    """Numbered stages on the terminal, each with its wall time.

    Parameters
    ----------
    total : int
        The number of stages (shown as ``[k/total]``).
    """

    def __init__(self, total: int):
        self.total = total
        self.k = 0
        self.t0 = time.perf_counter()
        self.t_stage = self.t0
        self.timings: list[tuple[str, float]] = []
        self.name = ""

    def start(self, name: str):
        """Close the running stage and open the next one."""
        self.finish()
        self.k += 1
        self.name = name
        self.t_stage = time.perf_counter()
        click.echo(click.style(f"[{self.k}/{self.total}] {name} ...", bold=True))

    def finish(self):
        """Close the running stage (its wall time is kept and shown)."""
        if self.name:
            dt = time.perf_counter() - self.t_stage
            self.timings.append((self.name, dt))
            click.echo(f"      done in {dt:.1f} s")
            self.name = ""

    @property
    def elapsed(self) -> float:
        """Wall time since the first stage [s]."""
        return time.perf_counter() - self.t0


def _twin_bar(desc):
    """A progress callback for the twin's steps and the function that closes its bar."""
    state = {"bar": None, "done": 0}

    def step(done):
        if state["bar"] is None:
            state["bar"] = tqdm(unit="s", desc=desc, leave=False)
        state["bar"].update(done - state["done"])
        state["done"] = done

    def close():
        if state["bar"] is not None:
            state["bar"].close()

    return step, close


def _fmt(v, digits=4):
    """A number for a person (``digits`` significant figures, never e-notation)."""
    return units.readable(v, digits)


@dataclass
class DemoRun:
    """Everything the demo made, step by step (the report and the summary read it)."""

    out: Path
    clean: object = None  # PrintRecord of print 1
    faulty: object = None  # PrintRecord of print 2 (with truth)
    onset_s: float = float("nan")
    video: Path | None = None
    faulty_video: object = None  # print 2 with L_w/L_o from the video
    features: object = None  # DataFrame, one row per frame
    annotated: dict | None = None
    vision_error_um: float = float("nan")
    store_path: Path | None = None
    first: object = None  # IngestResult of print 1
    second: object = None  # IngestResult of print 2
    forecast_keep: object = None
    forecast_change: object = None
    advice: object = None
    advice_after: str = "now"  # the machine the advice is for ("once the nozzle is cleaned")
    faults: list | None = None  # print 2's open faults (cause, onset, what to do)

    @property
    def events(self) -> list:
        """Print 2's alarm events."""
        return self.second.detection.events

    @property
    def after_onset(self) -> list:
        """Print 2's events detected at or after the true onset."""
        return [ev for ev in self.events if ev.detected_s >= self.onset_s]

    @property
    def before_onset(self) -> list:
        """Print 2's events detected before the true onset (false alarms)."""
        return [ev for ev in self.events if ev.detected_s < self.onset_s]

    @property
    def delay_s(self) -> float:
        """Delay of the first alarm after the onset [s] (NaN: not detected)."""
        after = self.after_onset
        return after[0].detected_s - self.onset_s if after else float("nan")


def simulate_prints(run: DemoRun, seed: int, clean_min, fault_min, onset_min) -> None:
    """Step 1: a clean print, then one whose nozzle clogs, both written to the demo folder."""
    if not 0 < onset_min < fault_min or clean_min <= 0:
        raise click.BadParameter("need 0 < onset-min < fault-min and clean-min > 0")
    run.clean = simulate("exp1", seed=seed + 1, duration_min=clean_min)
    run.clean.meta["machine_id"] = MACHINE
    run.faulty = simulate(
        "nozzle_clog",
        seed=seed + 2,
        duration_min=fault_min,
        overrides={"fault": {"onset_min": onset_min}},
        continue_from=run.clean,
    )
    run.onset_s = float(run.faulty.meta["fault_onset_s"])
    write_record(run.clean, run.out / "print1_clean.parquet")
    write_record(run.faulty, run.out / "print2_nozzle_clog.parquet")
    config = run.faulty.meta.get("scenario_config")
    click.echo(
        f"      print 1: exp1, {clean_min:g} min; print 2: nozzle_clog, {fault_min:g} min, "
        f"clog from {run.onset_s / 60:g} min (deposition rate ×"
        f"{config['fault']['nozzle_deposition_multiplier']:g})"
        if config is not None
        else f"      print 2 clogs from {run.onset_s / 60:g} min"
    )


def render_camera_video(run: DemoRun, seed: int) -> None:
    """Step 2: the alignment-camera video of print 2 (``ajtwin render``'s library call)."""
    run.video = run.out / "print2_camera.mp4"
    video = render_record_video(
        run.faulty,
        run.video,
        fps=VIDEO_FPS,
        shape=VIDEO_SHAPE,
        settings=RenderSettings.from_defaults(tilt_deg=0.0, um_per_px=UM_PER_PX),
        seed=seed,
        truth=TruthFile(extra={"record": str(run.out / "print2_nozzle_clog.parquet")}),
    )
    for note in video.notes:
        click.echo(f"note: {note}")
    click.echo(f"wrote {run.video} and {video.truth_path}")


def extract_from_video(run: DemoRun) -> None:
    """Step 3: linewidth/overspray of print 2 from its video, joined into the record."""
    snapshot_times = (60.0, run.onset_s + 0.8 * (run.faulty.duration_s - run.onset_s))
    run.faulty_video, join_summary, run.features, run.annotated = join_video(
        run.faulty, run.video, UM_PER_PX, annotate_times=snapshot_times
    )
    write_record(run.faulty_video, run.out / "print2_from_video.parquet")
    run.features.to_csv(run.out / "print2_video_features.csv", index=False)
    lw_true = run.faulty.data["linewidth_um"].to_numpy()
    lw_video = run.faulty_video.data["linewidth_um"].to_numpy()
    both = np.isfinite(lw_true) & np.isfinite(lw_video)
    run.vision_error_um = (
        float(np.median(np.abs(lw_video[both] - lw_true[both]))) if both.any() else np.nan
    )
    click.echo(
        f"      {len(run.features)} frames, {join_summary['seconds_filled']} seconds with "
        f"L_w/L_o from video; median |video − logged line| = {run.vision_error_um:.2f} µm"
    )


def ingest_prints(run: DemoRun) -> Registry:
    """Step 4: a fresh registry, the machine, both prints (the second from the first's end)."""
    run.store_path = run.out / "registry.sqlite"
    for suffix in ("", "-wal", "-shm"):
        Path(str(run.store_path) + suffix).unlink(missing_ok=True)
    reg = Registry(run.store_path)
    reg.add_machine(MACHINE, notes="virtual AJ 300 of the demo")
    step, close = _twin_bar("twin, print 1")
    try:
        run.first = ingest_record(
            reg, MACHINE, run.clean, source="print1_clean.parquet", progress=step, keep_run=True
        )
    finally:
        close()
    step, close = _twin_bar("twin, print 2")
    try:
        run.second = ingest_record(
            reg,
            MACHINE,
            run.faulty_video,
            source="print2_from_video.parquet",
            progress=step,
            keep_run=True,
        )
    finally:
        close()
    again = ingest_record(reg, MACHINE, run.faulty_video, source="again")
    click.echo(
        f"      print 1: {run.first.seconds:.0f} s; print 2 (started from print 1's end state "
        f"and θ): {run.second.seconds:.0f} s; re-ingest detected as duplicate: {again.duplicate}"
    )
    return reg


def echo_alarms(run: DemoRun) -> None:
    """Step 5: print 2's alarms as the detectors raised them."""
    for ev in run.events:
        click.echo(
            click.style(
                f"      ALARM at {ev.detected_s / 60:.2f} min (onset est. {ev.onset_s / 60:.2f} "
                f"min): {ev.description}",
                fg="red",
            )
        )
        click.echo(f"        what to do: {alarm_sentence(ev.cause, ev.onset_s, MACHINE)}")
    if not run.events:
        click.echo("      no alarm")


def forecast_and_advise(run: DemoRun, reg: Registry) -> None:
    """Step 6: from the machine's current state, a forecast (inputs kept, and Q_c → 26
    sccm) and input advice for a 43 µm line."""
    last = reg.last_print(MACHINE)
    twin = Twin.default()
    twin.theta = np.asarray(last["theta_after"])
    u_now = np.nanmedian(run.faulty_video.inputs[-60:], axis=0)
    start = (twin, last["end_mean"], last["end_cov"])
    run.forecast_keep = forecast(*start, input_schedule(u_now, [], HORIZON_S))
    change = [parse_change("carrier_flow_sccm=26@+60s")]
    run.forecast_change = forecast(*start, input_schedule(u_now, change, HORIZON_S))
    run.forecast_keep.to_frame().to_csv(run.out / "forecast_keep.csv", index=False)
    run.forecast_change.to_frame().to_csv(run.out / "forecast_carrier26.csv", index=False)
    # advice is for the machine as it will be: a clog is cleaned first (`advise` refuses a
    # machine with an open fault), so the demo advises from the cleaned nozzle
    run.faults = open_faults(run.events, [], MACHINE)
    cleaned = [{"nozzle_cleaned": True}] if any("nozzle" in f["cause"] for f in run.faults) else []
    mean, cov, theta = apply_maintenance(last["end_mean"], last["end_cov"], twin.theta, cleaned)
    advised = Twin.default()
    advised.theta = theta
    run.advice = advise(
        advised,
        mean,
        cov,
        u_now,
        TARGET_UM,
        max_overspray_um=MAX_OVERSPRAY_UM,
        limits=reg.machine(MACHINE)["limits"],
    )
    run.advice_after = "once the nozzle is cleaned" if cleaned else "now"
    click.echo(f"      advice for L_w {TARGET_UM:g} µm {run.advice_after}: {run.advice.message}")
    if run.advice.at_limits:
        click.echo(f"      note: {run.advice.limit_note()}")


def _report_runs(run: DemoRun) -> list[dict]:
    """The two prints as the report's figures take them."""
    return [
        {
            "label": "print 1 (clean)",
            "time_s": run.first.run.time_s,
            "measured": run.clean.outputs,
            "predicted": np.asarray(run.first.run.filtered.predicted_outputs),
            "means": run.first.run.means,
            "stds": run.first.run.stds,
            "truth": run.clean.true_states,
            "events": run.first.detection.events,
            "fault_onset_s": None,
        },
        {
            "label": "print 2 (nozzle clog, video)",
            "time_s": run.second.run.time_s,
            "measured": run.faulty_video.outputs,
            "predicted": np.asarray(run.second.run.filtered.predicted_outputs),
            "means": run.second.run.means,
            "stds": run.second.run.stds,
            "truth": run.faulty.true_states,
            "events": run.events,
            "fault_onset_s": run.onset_s,
        },
    ]


def _state_table(run: DemoRun) -> str:
    """Print 2's states ± 2σ against the truth at a few times (φ_A in ppm by volume), and
    how well φ_A's level is known."""
    truth = run.faulty.true_states
    scale = report.STATE_SCALE
    rows = []
    for frac in (0.1, 0.3, 0.5, 0.6, 0.75, 0.9, 1.0):
        k = min(int(frac * len(truth)), len(truth) - 1)
        m, s = run.second.run.means[k] * scale, run.second.run.stds[k] * scale
        cells = [
            f"{_fmt(m[i])} ± {_fmt(2 * s[i], 2)} (true {_fmt(truth[k, i] * scale[i])})"
            for i in (0, 1, 3, 4)
        ]
        rows.append([f"{k / 60:.1f}", *cells])
    labels = [report.STATE_LABELS[i] for i in (0, 1, 3, 4)]
    table = report.table_html(["print 2 time [min]", *labels], rows)
    return table + f"<p class='note'>{html.escape(aerosol_level_note(None))}.</p>"


def _alarm_table(run: DemoRun) -> str:
    """Print 2's alarms: when, the estimated onset, the delay, the cause, the detectors."""
    rows = [
        [
            f"{ev.detected_s / 60:.2f}",
            f"{ev.onset_s / 60:.2f}",
            f"{(ev.detected_s - run.onset_s):.0f}"
            if ev.detected_s >= run.onset_s
            else "false alarm",
            alarm_sentence(ev.cause, ev.onset_s, MACHINE),
            "; ".join(detector_words(d) for d in ev.detectors),
        ]
        for ev in run.events
    ]
    return report.table_html(
        ["detected [min]", "onset est. [min]", "delay [s]", "likely cause and what to do",
         "detectors"],
        rows or [["–", "–", "–", "no alarm", "–"]],
    )  # fmt: skip


def _advice_table(run: DemoRun) -> str:
    """The inputs now and the advised ones (± 2σ)."""
    return report.table_html(
        ["", "now", f"advised (±2σ, after {run.advice.settle_s} s)"],
        [
            [name, _fmt(now), _fmt(new) if std is None else f"{_fmt(new)} ± {_fmt(2 * std, 2)}"]
            for name, now, new, std in run.advice.rows()
        ],
    )


def _summary_html(run: DemoRun) -> str:
    """The report's first section: the fault, the alarm and how the line was measured."""
    after = run.after_onset
    alarm = (
        f"<span class='alarm'>The twin raised the alarm at {after[0].detected_s / 60:.2f} min"
        f" — {run.delay_s:.0f} s after the onset — and labelled it: {after[0].description}."
        f" What to do: {html.escape(alarm_sentence(after[0].cause, after[0].onset_s, MACHINE))}"
        "</span>"
        if after
        else "<span class='alarm'>The fault was not detected.</span>"
    )
    return (
        f"<p>Machine <b>{MACHINE}</b>, two virtual prints. Print 2's nozzle starts to clog at "
        f"<b>{run.onset_s / 60:.1f} min</b> (true onset). "
        + alarm
        + f" False alarms before the onset: {len(run.before_onset)} (print 1: "
        f"{len(run.first.detection.events)}).</p>"
        "<p class='note'>L_w and L_o of print 2 come from its rendered alignment-camera video "
        f"({len(run.features)} frames, {VIDEO_FPS:g} frame/s, {UM_PER_PX} µm/px; median "
        f"deviation from the logged line {run.vision_error_um:.2f} µm); P_c, P_s from the MFC "
        "log; Q_m from the record (the profile CNN needs training that does not fit the "
        "demo's time).</p>"
    )


def write_report(run: DemoRun, stages: Stages) -> Path:
    """Step 7: ``report.html``, one self-contained page (figures embedded)."""
    runs = _report_runs(run)
    frames_html = "".join(
        report.img_tag(report.frame_png(img), f"frame at {t:.0f} s")
        for t, img in run.annotated.items()
    )
    timing_table = report.table_html(
        ["stage", "wall time [s]"], [[n, f"{dt:.1f}"] for n, dt in stages.timings]
    )
    warn = "".join(f"<p class='note'>Forecast: {w}</p>" for w in run.forecast_keep.warnings)
    forecasts = (
        report.img_tag(
            report.forecast_figure(run.forecast_keep, "Keep the inputs (15 min, ±2σ)"),
            "forecast keep",
        )
        + report.img_tag(
            report.forecast_figure(run.forecast_change, "Q_c → 26 sccm at +60 s (±2σ)"),
            "forecast change",
        )
        + warn
    )
    fits = [
        ("print 1", run.first.summary.get("mismatch")),
        ("print 2", run.second.summary.get("mismatch")),
    ]
    sections = [
        ("Summary", _summary_html(run)),
        ("Model–machine fit (mismatch guard)", report.mismatch_html(fits)),
        ("Alarms", _alarm_table(run)),
        ("Outputs", report.img_tag(report.outputs_figure(runs), "outputs")),
        ("Hidden states", report.img_tag(report.states_figure(runs), "states") + _state_table(run)),
        (
            "Detectors",
            report.img_tag(report.detectors_figure(run.second.detection, run.onset_s), "detectors"),
        ),
        ("Alignment camera (annotated: linewidth red, overspray blue)", frames_html),
        ("Forecast from the end of print 2 (learned θ)", forecasts),
        (
            f"Input advice for L_w = {TARGET_UM:g} µm (L_o ≤ {MAX_OVERSPRAY_UM:g} µm)",
            _advice_table(run)
            + f"<p>Advised {run.advice_after}: {html.escape(run.advice.message)}.</p>"
            + (
                f"<p class='note'>{html.escape(run.advice.limit_note())}.</p>"
                if run.advice.at_limits
                else ""
            ),  # fmt: skip
        ),
        ("Run", timing_table + f"<p class='note'>Registry: {run.store_path}</p>"),
    ]
    page = report.html_page("ajtwin demo: nozzle clog on a virtual AJ printer", sections)
    path = run.out / "report.html"
    path.write_text(page, encoding="utf-8")
    return path


def echo_summary(run: DemoRun, stages: Stages) -> None:
    """The terminal summary: detection, the end state against the truth, forecast, advice."""
    click.echo("")
    click.echo(click.style("Summary", bold=True))
    click.echo(f"  true nozzle-clog onset: {run.onset_s / 60:.1f} min into print 2")
    after = run.after_onset
    if after:
        click.echo(
            f"  detected at {after[0].detected_s / 60:.2f} min → delay {run.delay_s:.0f} s; "
            f"cause: {after[0].description}"
        )
    else:
        click.echo("  fault NOT detected")
    click.echo(f"  false alarms: {len(run.before_onset) + len(run.first.detection.events)}")
    end, truth = run.second.run.end_mean, run.faulty.true_states
    k = len(truth) - 1
    click.echo(
        f"  end of print 2: ΔR_N {end[3]:.3f} µm (true {truth[k, 3]:.3f}), "
        f"d_a {end[0]:.2f} µm (true {truth[k, 0]:.2f})"
    )
    y_keep, s_keep = run.forecast_keep.output_means[-1], run.forecast_keep.output_stds[-1]
    click.echo(
        f"  forecast +15 min, inputs kept: L_w {y_keep[0]:.1f} ± {2 * s_keep[0]:.1f} µm, "
        f"P_c {y_keep[2]:.0f} ± {2 * s_keep[2]:.0f} Pa"
    )
    for w in run.forecast_keep.warnings:
        click.echo(f"  forecast warning: {w}")
    u = run.advice.inputs
    click.echo(
        f"  advice for L_w {TARGET_UM:g} µm {run.advice_after}: I_A {u[0]:.0f} mA, Q_c "
        f"{u[1]:.1f}, Q_s {u[2]:.1f} sccm ({run.advice.message})"
    )
    if run.advice.at_limits:
        click.echo(f"    note: {run.advice.limit_note()}")
    for fault in run.faults or ():
        click.echo(click.style(f"  what to do: {fault['sentence']}", bold=True))
        click.echo(f"    (the demo's machine is kept in {run.store_path}: add --store to it)")
    click.echo(f"  total wall time {stages.elapsed:.0f} s")
    click.echo(f"  report: {run.out / 'report.html'}")
    click.echo(
        f"  dashboard: ajtwin dashboard --store {run.store_path}  → open http://127.0.0.1:8050/ "
        "(add --virtual-print nozzle_clog to watch a live print)"
    )


def run_demo(
    out_dir,
    seed: int = 0,
    clean_min: float = CLEAN_MIN,
    fault_min: float = FAULT_MIN,
    onset_min: float = FAULT_ONSET_MIN,
) -> DemoRun:
    """The whole demo (module docstring): seven stages, the report, the summary.

    Parameters
    ----------
    out_dir : path
        Folder for the demo's files (report.html, video, registry).
    seed : int
        Seed of the virtual prints.
    clean_min, fault_min : float
        Length of the clean and of the faulty print [min].
    onset_min : float
        When the nozzle starts to clog in the faulty print [min].
    """
    run = DemoRun(Path(out_dir))
    run.out.mkdir(parents=True, exist_ok=True)
    stages = Stages(7)
    stages.start("virtual printer: a clean print, then a print whose nozzle clogs")
    simulate_prints(run, seed, clean_min, fault_min, onset_min)
    stages.start(f"render the alignment-camera video of print 2 ({VIDEO_FPS:g} frame/s)")
    render_camera_video(run, seed)
    stages.start("extract linewidth/overspray from the video (paper App. A)")
    extract_from_video(run)
    stages.start("machine registry: ingest both prints (twin: EKF + EM)")
    reg = ingest_prints(run)
    stages.start("anomaly detection on the innovations")
    echo_alarms(run)
    stages.start("forecast and input advice from the machine's current state")
    forecast_and_advise(run, reg)
    stages.start("write demo-output/report.html")
    write_report(run, stages)
    stages.finish()
    reg.close()
    echo_summary(run, stages)
    return run


if __name__ == "__main__":
    run_demo("demo-output")
