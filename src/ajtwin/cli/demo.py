"""``ajtwin demo``: the twin in use, end to end, on a virtual machine with a fault.

The steps are :mod:`ajtwin.studies.demo`'s (``--live``: :mod:`ajtwin.studies.live_demo`).
"""

from __future__ import annotations

import logging
import time

import click


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
# hidden: shorter prints for tests (default: the demo's 15, 40 and 20 min)
@click.option("--clean-min", type=float, default=None, hidden=True)
@click.option("--fault-min", type=float, default=None, hidden=True)
@click.option("--onset-min", type=float, default=None, hidden=True)
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
    # lazy CLI loading: the demo loads JAX, OpenCV and matplotlib when it runs
    from ajtwin.studies.demo import run_demo

    lengths = {"clean_min": clean_min, "fault_min": fault_min, "onset_min": onset_min}
    run_demo(out_dir, seed, **{k: v for k, v in lengths.items() if v is not None})


def _wait_for_ctrl_c():
    """Sleep until Ctrl-C (KeyboardInterrupt)."""
    while True:
        time.sleep(1.0)


def _live_demo(out_dir, seed, port=0, keep_open=False):
    """``--live``: the virtual printer over OPC UA, the live twin and the dashboard."""
    # lazy CLI loading: the live demo loads asyncua, uvicorn and JAX when it runs; the
    # module (not the function) so that a test can stand in for its parts
    from ajtwin.studies import live_demo

    logging.basicConfig(level=logging.WARNING, format="      %(message)s")
    logging.getLogger("asyncua").setLevel(logging.ERROR)

    def report(summary):
        alarm = summary["alarm"]
        if alarm is None:
            click.echo("  fault NOT detected")
        else:
            # lazy CLI loading: imported when the command runs, not for --help
            from ajtwin.apps.detection.causes import cause_action

            click.echo(
                click.style(
                    f"  ALARM at {alarm['detected_s'] / 60:.1f} min, {summary['delay_s']:.0f} s "
                    f"after the clog began: {alarm['description']}",
                    fg="red",
                )
            )
            if alarm.get("cause"):
                click.echo(f"  what to do: {cause_action(alarm['cause'], summary.get('machine'))}")
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
        live_demo.run_live_demo(out_dir, seed, echo=click.echo, dashboard_port=port, after=report)
    except RuntimeError as exc:  # e.g. the dashboard's port is taken
        raise click.ClickException(str(exc)) from None
