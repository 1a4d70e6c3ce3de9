"""``ajtwin demo``: the twin in use, end to end, on a virtual machine with a fault.

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
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import click
import numpy as np

CLEAN_MIN = 15.0
FAULT_MIN = 40.0
FAULT_ONSET_MIN = 20.0
VIDEO_FPS = 0.1
VIDEO_SIZE = "640x400"
UM_PER_PX = 0.75
MACHINE = "demo-aj300"


class _Stages:
    def __init__(self, total: int):
        self.total = total
        self.k = 0
        self.t0 = time.perf_counter()
        self.t_stage = self.t0
        self.timings: list[tuple[str, float]] = []
        self.name = ""

    def start(self, name: str):
        self.finish()
        self.k += 1
        self.name = name
        self.t_stage = time.perf_counter()
        click.echo(click.style(f"[{self.k}/{self.total}] {name} ...", bold=True))

    def finish(self):
        if self.name:
            dt = time.perf_counter() - self.t_stage
            self.timings.append((self.name, dt))
            click.echo(f"      done in {dt:.1f} s")
            self.name = ""

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0


def _twin_bar(desc):
    from tqdm import tqdm

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
    return f"{v:.{digits}g}"


@click.command("demo")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="demo-output",
    show_default=True,
    help="Folder for the demo's files (report.html, video, registry).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the virtual prints.")
@click.option("--clean-min", type=float, default=CLEAN_MIN, show_default=True, hidden=True)
@click.option("--fault-min", type=float, default=FAULT_MIN, show_default=True, hidden=True)
@click.option("--onset-min", type=float, default=FAULT_ONSET_MIN, show_default=True, hidden=True)
@click.option(
    "--live",
    is_flag=True,
    help="Instead: the virtual printer over OPC UA, the live twin beside it and the dashboard "
    "served live from it (~1 min).",
)
@click.option(
    "--port",
    type=click.IntRange(min=0, max=65535),
    default=0,
    show_default=True,
    help="--live: serve the dashboard on 127.0.0.1:PORT (0: a free port).",
)
@click.option(
    "--keep-open",
    is_flag=True,
    help="--live: keep serving the dashboard after the print ends, until Ctrl-C.",
)
def demo_command(out_dir, seed, clean_min, fault_min, onset_min, live, port, keep_open):
    """Run the end-to-end demo: virtual print with a nozzle clog → camera video → vision →
    twin → alarm → forecast → advice → demo-output/report.html."""
    if live:
        return _live_demo(out_dir, seed, port, keep_open)
    if keep_open or port:
        raise click.UsageError("--port and --keep-open go with --live")
    from ajtwin.apps import report
    from ajtwin.apps.planning.advice import advise
    from ajtwin.apps.planning.forecast import forecast, input_schedule, parse_change
    from ajtwin.cli.vision import render
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.engine.video import join_video
    from ajtwin.estimation import Twin
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate
    from ajtwin.store.registry import Registry

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stages = _Stages(7)

    # 1 ---------------------------------------------------------------- virtual printer
    stages.start("virtual printer: a clean print, then a print whose nozzle clogs")
    if not 0 < onset_min < fault_min or clean_min <= 0:
        raise click.BadParameter("need 0 < onset-min < fault-min and clean-min > 0")
    clean = simulate("exp1", seed=seed + 1, duration_min=clean_min)
    clean.meta["machine_id"] = MACHINE
    faulty = simulate(
        "nozzle_clog",
        seed=seed + 2,
        duration_min=fault_min,
        overrides={"fault": {"onset_min": onset_min}},
        continue_from=clean,
    )
    onset_s = float(faulty.meta["fault_onset_s"])
    write_record(clean, out / "print1_clean.parquet")
    write_record(faulty, out / "print2_nozzle_clog.parquet")
    click.echo(
        f"      print 1: exp1, {clean_min:g} min; print 2: nozzle_clog, {fault_min:g} min, "
        f"clog from {onset_s / 60:g} min (deposition rate ×"
        f"{faulty.meta['scenario_config']['fault']['nozzle_deposition_multiplier']:g})"
        if "scenario_config" in faulty.meta
        else f"      print 2 clogs from {onset_s / 60:g} min"
    )

    # 2 ---------------------------------------------------------------- camera video
    stages.start(f"render the alignment-camera video of print 2 ({VIDEO_FPS:g} frame/s)")
    video = out / "print2_camera.mp4"
    render.main(
        [
            str(out / "print2_nozzle_clog.parquet"),
            "--out",
            str(video),
            "--fps",
            str(VIDEO_FPS),
            "--size",
            VIDEO_SIZE,
            "--um-per-px",
            str(UM_PER_PX),
            "--seed",
            str(seed),
        ],
        standalone_mode=False,
    )

    # 3 ---------------------------------------------------------------- vision
    stages.start("extract linewidth/overspray from the video (paper App. A)")
    snapshot_times = (60.0, onset_s + 0.8 * (faulty.duration_s - onset_s))
    faulty_video, join_summary, features, annotated = join_video(
        faulty, video, UM_PER_PX, annotate_times=snapshot_times
    )
    write_record(faulty_video, out / "print2_from_video.parquet")
    features.to_csv(out / "print2_video_features.csv", index=False)
    lw_true = faulty.data["linewidth_um"].to_numpy()
    lw_video = faulty_video.data["linewidth_um"].to_numpy()
    both = np.isfinite(lw_true) & np.isfinite(lw_video)
    vision_err = float(np.median(np.abs(lw_video[both] - lw_true[both]))) if both.any() else np.nan
    click.echo(
        f"      {len(features)} frames, {join_summary['seconds_filled']} seconds with L_w/L_o "
        f"from video; median |video − logged line| = {vision_err:.2f} µm"
    )

    # 4 ---------------------------------------------------------------- registry + twin
    stages.start("machine registry: ingest both prints (twin: EKF + EM)")
    store_path = out / "registry.sqlite"
    for suffix in ("", "-wal", "-shm"):
        Path(str(store_path) + suffix).unlink(missing_ok=True)
    reg = Registry(store_path)
    reg.add_machine(MACHINE, notes="virtual AJ 300 of the demo")
    step, close = _twin_bar("twin, print 1")
    try:
        first = ingest_record(reg, MACHINE, clean, source="print1_clean.parquet", progress=step)
    finally:
        close()
    step, close = _twin_bar("twin, print 2")
    try:
        second = ingest_record(
            reg, MACHINE, faulty_video, source="print2_from_video.parquet", progress=step
        )
    finally:
        close()
    again = ingest_record(reg, MACHINE, faulty_video, source="again")
    click.echo(
        f"      print 1: {first.seconds:.0f} s; print 2 (started from print 1's end state "
        f"and θ): {second.seconds:.0f} s; re-ingest detected as duplicate: {again.duplicate}"
    )

    # 5 ---------------------------------------------------------------- anomalies
    stages.start("anomaly detection on the innovations")
    detection = second.detection
    events = detection.events
    after = [ev for ev in events if ev.detected_s >= onset_s]
    false_before = [ev for ev in events if ev.detected_s < onset_s]
    delay = after[0].detected_s - onset_s if after else float("nan")
    for ev in events:
        click.echo(
            click.style(
                f"      ALARM at {ev.detected_s / 60:.2f} min (onset est. {ev.onset_s / 60:.2f} "
                f"min): {ev.description}",
                fg="red",
            )
        )
    if not events:
        click.echo("      no alarm")

    # 6 ---------------------------------------------------------------- forecast, advice
    stages.start("forecast and input advice from the machine's current state")
    last = reg.last_print(MACHINE)
    twin = Twin.default()
    twin.theta = np.asarray(last["theta_after"])
    u_now = np.nanmedian(faulty_video.inputs[-60:], axis=0)
    horizon = 900
    fc_keep = forecast(twin, last["end_mean"], last["end_cov"], input_schedule(u_now, [], horizon))
    fc_change = forecast(
        twin,
        last["end_mean"],
        last["end_cov"],
        input_schedule(u_now, [parse_change("carrier_flow_sccm=26@+60s")], horizon),
    )
    fc_keep.to_frame().to_csv(out / "forecast_keep.csv", index=False)
    fc_change.to_frame().to_csv(out / "forecast_carrier26.csv", index=False)
    target = 43.0
    advice = advise(
        twin,
        last["end_mean"],
        last["end_cov"],
        u_now,
        target,
        max_overspray_um=35.0,
        limits=reg.machine(MACHINE)["limits"],
    )
    if not advice.reachable and after and after[0].cause == "nozzle_clog":
        advice.message += " — the nozzle is clogging: clean it, then advise again"
    click.echo(f"      advice for L_w {target:g} µm: {advice.message}")

    # 7 ---------------------------------------------------------------- report
    stages.start("write demo-output/report.html")
    runs = [
        {
            "label": "print 1 (clean)",
            "time_s": first.run.time_s,
            "measured": clean.outputs,
            "predicted": np.asarray(first.run.filtered.predicted_outputs),
            "means": first.run.means,
            "stds": first.run.stds,
            "truth": clean.true_states,
            "events": first.detection.events,
            "fault_onset_s": None,
        },
        {
            "label": "print 2 (nozzle clog, video)",
            "time_s": second.run.time_s,
            "measured": faulty_video.outputs,
            "predicted": np.asarray(second.run.filtered.predicted_outputs),
            "means": second.run.means,
            "stds": second.run.stds,
            "truth": faulty.true_states,
            "events": events,
            "fault_onset_s": onset_s,
        },
    ]
    truth = faulty.true_states
    rows = []
    for frac in (0.1, 0.3, 0.5, 0.6, 0.75, 0.9, 1.0):
        k = min(int(frac * len(truth)), len(truth) - 1)
        m, s = second.run.means[k], second.run.stds[k]
        rows.append(
            [f"{k / 60:.1f}"]
            + [
                f"{_fmt(m[i])} ± {_fmt(2 * s[i], 2)} (true {_fmt(truth[k, i])})"
                for i in (0, 1, 3, 4)
            ]
        )
    state_table = report.table_html(
        ["print 2 time [min]", "d_a [µm]", "V_l [mL]", "ΔR_N [µm]", "φ_A"], rows
    )
    alarm_rows = [
        [
            f"{ev.detected_s / 60:.2f}",
            f"{ev.onset_s / 60:.2f}",
            f"{(ev.detected_s - onset_s):.0f}" if ev.detected_s >= onset_s else "false alarm",
            ev.description,
            ", ".join(ev.detectors),
        ]
        for ev in events
    ]
    alarm_table = report.table_html(
        ["detected [min]", "onset est. [min]", "delay [s]", "likely cause", "detectors"],
        alarm_rows or [["–", "–", "–", "no alarm", "–"]],
    )
    advice_table = report.table_html(
        ["", "now", f"advised (±2σ, after {advice.settle_s} s)"],
        [
            [name, _fmt(now), _fmt(new) if std is None else f"{_fmt(new)} ± {_fmt(2 * std, 2)}"]
            for name, now, new, std in advice.rows()
        ],
    )
    frames_html = "".join(
        report.img_tag(report.frame_png(img), f"frame at {t:.0f} s") for t, img in annotated.items()
    )
    timing_table = report.table_html(
        ["stage", "wall time [s]"], [[n, f"{dt:.1f}"] for n, dt in stages.timings]
    )
    warn = "".join(f"<p class='note'>Forecast: {w}</p>" for w in fc_keep.warnings)
    summary_html = (
        f"<p>Machine <b>{MACHINE}</b>, two virtual prints. Print 2's nozzle starts to clog at "
        f"<b>{onset_s / 60:.1f} min</b> (true onset). "
        + (
            f"<span class='alarm'>The twin raised the alarm at {after[0].detected_s / 60:.2f} min"
            f" — {delay:.0f} s after the onset — and labelled it: {after[0].description}.</span>"
            if after
            else "<span class='alarm'>The fault was not detected.</span>"
        )
        + f" False alarms before the onset: {len(false_before)} (print 1: "
        f"{len(first.detection.events)}).</p>"
        "<p class='note'>L_w and L_o of print 2 come from its rendered alignment-camera video "
        f"({len(features)} frames, {VIDEO_FPS:g} frame/s, {UM_PER_PX} µm/px; median deviation "
        f"from the logged line {vision_err:.2f} µm); P_c, P_s from the MFC log; Q_m from the "
        "record (the profile CNN needs training that does not fit the demo's time).</p>"
    )
    sections = [
        ("Summary", summary_html),
        (
            "Model–machine fit (mismatch guard, docs/calibration.md)",
            report.mismatch_html(
                [
                    ("print 1", first.summary.get("mismatch")),
                    ("print 2", second.summary.get("mismatch")),
                ]
            ),
        ),
        ("Alarms", alarm_table),
        ("Outputs", report.img_tag(report.outputs_figure(runs), "outputs")),
        ("Hidden states", report.img_tag(report.states_figure(runs), "states") + state_table),
        ("Detectors", report.img_tag(report.detectors_figure(detection, onset_s), "detectors")),
        ("Alignment camera (annotated: linewidth red, overspray blue)", frames_html),
        (
            "Forecast from the end of print 2 (learned θ)",
            report.img_tag(
                report.forecast_figure(fc_keep, "Keep the inputs (15 min, ±2σ)"), "forecast keep"
            )
            + report.img_tag(
                report.forecast_figure(fc_change, "Q_c → 26 sccm at +60 s (±2σ)"),
                "forecast change",
            )
            + warn,
        ),
        (
            f"Input advice for L_w = {target:g} µm (L_o ≤ 35 µm)",
            advice_table + f"<p>{advice.message}</p>",
        ),
        ("Run", timing_table + f"<p class='note'>Registry: {store_path}</p>"),
    ]
    page = report.html_page("ajtwin demo: nozzle clog on a virtual AJ printer", sections)
    (out / "report.html").write_text(page, encoding="utf-8")
    stages.finish()
    reg.close()

    # terminal summary -------------------------------------------------------
    click.echo("")
    click.echo(click.style("Summary", bold=True))
    click.echo(f"  true nozzle-clog onset: {onset_s / 60:.1f} min into print 2")
    if after:
        click.echo(
            f"  detected at {after[0].detected_s / 60:.2f} min → delay {delay:.0f} s; "
            f"cause: {after[0].description}"
        )
    else:
        click.echo("  fault NOT detected")
    click.echo(f"  false alarms: {len(false_before) + len(first.detection.events)}")
    end = second.run.end_mean
    k = len(truth) - 1
    click.echo(
        f"  end of print 2: ΔR_N {end[3]:.3f} µm (true {truth[k, 3]:.3f}), "
        f"d_a {end[0]:.2f} µm (true {truth[k, 0]:.2f})"
    )
    y_keep = fc_keep.output_means[-1]
    s_keep = fc_keep.output_stds[-1]
    click.echo(
        f"  forecast +15 min, inputs kept: L_w {y_keep[0]:.1f} ± {2 * s_keep[0]:.1f} µm, "
        f"P_c {y_keep[2]:.0f} ± {2 * s_keep[2]:.0f} Pa"
    )
    for w in fc_keep.warnings:
        click.echo(f"  forecast warning: {w}")
    click.echo(
        f"  advice for L_w {target:g} µm: I_A {advice.inputs[0]:.0f} mA, Q_c "
        f"{advice.inputs[1]:.1f}, Q_s {advice.inputs[2]:.1f} sccm ({advice.message})"
    )
    click.echo(f"  total wall time {stages.elapsed:.0f} s")
    click.echo(f"  report: {out / 'report.html'}")
    click.echo(
        f"  dashboard: ajtwin dashboard --store {store_path}  → open http://127.0.0.1:8050/ "
        "(add --virtual-print nozzle_clog to watch a live print)"
    )
    if shutil.which("xdg-open") is None:
        pass


def _wait_for_ctrl_c():
    while True:
        time.sleep(1.0)


def _live_demo(out_dir, seed, port=0, keep_open=False):
    import logging

    from ajtwin.live.demo import run_live_demo

    logging.basicConfig(level=logging.WARNING, format="      %(message)s")
    logging.getLogger("asyncua").setLevel(logging.ERROR)

    def report(summary):
        alarm = summary["alarm"]
        if alarm is None:
            click.echo("  fault NOT detected")
        else:
            click.echo(
                click.style(
                    f"  ALARM at {alarm['detected_s']:.0f} s, {summary['delay_s']:.0f} s after "
                    f"the clog began: {alarm['description']}",
                    fg="red",
                )
            )
        got = [e for e in summary["events_received_by_second_client"] if e["state"] == "raised"]
        click.echo(f"  alarm events received by a second OPC UA client: {len(got)}")
        click.echo(
            f"  false alarms: {summary['false_alarms']}; wall time {summary['wall_s']:.0f} s"
        )
        click.echo(f"  registry: {summary['registry']}")
        if keep_open:
            # the dashboard thread serves on; this thread only waits for Ctrl-C
            click.echo(f"  dashboard still at {summary['dashboard_url']}; Ctrl-C stops it")
            try:
                _wait_for_ctrl_c()
            except KeyboardInterrupt:
                click.echo("  stopped")
        else:
            click.echo(
                f"  dashboard stopped with the demo (--keep-open keeps it); to browse this "
                f"registry: ajtwin dashboard --store {summary['registry']}"
            )

    click.echo(click.style("live twin over OPC UA, dashboard served live", bold=True))
    try:
        run_live_demo(out_dir, seed, echo=click.echo, dashboard_port=port, after=report)
    except RuntimeError as exc:  # e.g. the dashboard's port is taken
        raise click.ClickException(str(exc)) from None
