"""``ajtwin live``: the live twin beside a machine, over OPC UA or a growing CSV
(docs/howto/run-the-live-twin.md)."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import click

from ajtwin.cli.options import (
    BoundedFloat,
    ToleranceType,
    configure_logging,
    open_registry,
    record_options,
    store_option,
    transition_option,
    transition_overrides,
)
from ajtwin.engine.messages import FinishedMessage
from ajtwin.store.live_log import CLAIMANT
from ajtwin.store.registry import RegistryError


@click.command()
@click.option("--machine", "machines", multiple=True, required=True, help="Machine name(s).")
@click.option("--opcua", "url", default=None, help="Server endpoint, opc.tcp://host:port.")
@click.option("--follow", "follow", type=click.Path(path_type=Path), default=None)
@click.option("--idle-timeout", type=float, default=None, help="--follow: close after S idle.")
@click.option("--username", default=None)
@click.option("--password", default=None, envvar="AJTWIN_OPCUA_PASSWORD")
@click.option("--certificate", type=click.Path(path_type=Path), default=None)
@click.option("--private-key", type=click.Path(path_type=Path), default=None)
@click.option(
    "--generate-certificate", is_flag=True, help="Create a self-signed client certificate."
)
@click.option("--server-certificate", type=click.Path(path_type=Path), default=None)
@click.option(
    "--security",
    default=None,
    type=click.Choice(["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign"]),
)
@click.option("--messages", type=click.Path(path_type=Path), default=None, help="JSON lines out.")
@click.option("--max-backoff", type=float, default=10.0, show_default=True, help="Reconnect [s].")
@click.option(
    "--dashboard",
    "dashboard_port",
    type=click.IntRange(min=0, max=65535),
    default=None,
    metavar="PORT",
    help="Also serve the browser dashboard from this process on 127.0.0.1:PORT (0: a free port); "
    "it keeps serving after the prints end, until Ctrl-C.",
)
@transition_option
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="The machine program the machines run (.prg): kept with each stored print, and with "
    "--dashboard the machine page shows the part map filling in (time 0 = program start).",
)
@click.option("--process-speed", "process_speed", type=BoundedFloat(0.0, 10_000.0),
              default=None, help="With --job: the GUI's process speed [mm/s].")  # fmt: skip
@click.option("--rapid-speed", "rapid_speed", type=BoundedFloat(0.0, 10_000.0),
              default=None, help="With --job: the GUI's rapid speed [mm/s].")  # fmt: skip
@click.option(
    "--tolerance",
    type=ToleranceType(),
    default=None,
    help="With --job: the part's linewidth tolerance in µm (45±3, 45+-3, 42:48).",
)
@click.option("--verbose", is_flag=True)
@record_options
@store_option
def live(
    machines,
    url,
    follow,
    idle_timeout,
    username,
    password,
    certificate,
    private_key,
    generate_certificate,
    server_certificate,
    security,
    messages,
    max_backoff,
    dashboard_port,
    transition,
    program,
    process_speed,
    rapid_speed,
    tolerance,
    verbose,
    csv_dialect,
    aliases,
    store,
):
    """Run the live twin beside a machine (OPC UA, or a growing CSV with --follow)."""

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.live.link import LinkRefused, OpcUaLink, OpcUaLogin, follow_csv

    configure_logging(verbose)
    if (url is None) == (follow is None):
        raise click.UsageError("give exactly one of --opcua URL or --follow FILE")
    if follow is not None and len(machines) != 1:
        raise click.UsageError("--follow follows one --machine")
    overrides = transition_overrides(transition)
    entry = _job(program, process_speed, rapid_speed, tolerance)
    registry = open_registry(store, create=True)  # the live twin writes
    engine = LiveEngine(registry, twin_overrides=overrides or None)
    try:  # one twin a machine: another one writing it (another PC of the lab) refuses this
        for name in machines:
            engine.log.registry.claim_machine(name, CLAIMANT)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    engine.warm_up(len(machines))
    engine.jobs.update(dict.fromkeys(machines, entry) if entry else {})  # stored with prints
    engine.subscribe(ConsoleReadiness(click.echo))
    out = None
    if messages is not None:
        out = messages.open("a", encoding="utf-8")
        engine.subscribe(
            lambda m: out.write(json.dumps(m.to_dict(), default=str) + "\n") or out.flush()
        )
    dashboard = None
    if dashboard_port is not None:
        dashboard = _serve_dashboard(engine, registry, machines, entry, tolerance, dashboard_port)
    if generate_certificate:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.live.printer_server import ensure_certificate

        if certificate is None or private_key is None:
            raise click.UsageError("--generate-certificate needs --certificate and --private-key")
        asyncio.run(
            ensure_certificate(certificate, private_key, "localhost", "urn:ajtwin:live-client")
        )
    link, ended = None, False
    try:
        if follow is not None:
            print_id = asyncio.run(
                follow_csv(
                    follow,
                    machines[0],
                    engine,
                    idle_timeout_s=idle_timeout,
                    aliases=aliases,
                    dialect=csv_dialect,
                )
            )
            if print_id is not None:
                click.echo(f"print stored as registry print id {print_id}")
            ended = True
        else:
            link = OpcUaLink(
                url,
                list(machines),
                engine,
                login=OpcUaLogin(
                    username=username,
                    password=password,
                    security=security,
                    certificate=certificate,
                    private_key=private_key,
                    server_certificate=server_certificate,
                ),
                max_backoff_s=max_backoff,
            )
            asyncio.run(link.run())
            click.echo(f"followed {', '.join(machines)} to the end of their prints")
            ended = len(link.finished) == len(machines)
        _keep_serving(dashboard)
    except LinkRefused as exc:
        raise click.ClickException(str(exc)) from None
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    except KeyboardInterrupt:
        if ended:
            click.echo("stopped (the prints had ended and are stored)", err=True)
        else:
            click.echo(
                "stopped; the live session stays open and resumes on the next start", err=True
            )
    finally:
        engine.shutdown()
        if out is not None:
            out.close()
        if dashboard is not None:
            dashboard.stop()


def _serve_dashboard(engine, registry, machines, entry, tolerance, port: int):
    """The dashboard in a thread of this process, every engine message pushed to it."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.web.publisher import LivePublisher
    from ajtwin.web.server import BackgroundServer

    publisher = LivePublisher()
    engine.subscribe(publisher.publish_engine)
    for name in machines:
        publisher.open_print(name)
    if entry is not None:
        _follow_parts(engine, publisher, machines, entry, tolerance)
    dashboard = BackgroundServer(registry.path, publisher, port=port)
    click.echo(f"dashboard: open {dashboard.url}", err=True)
    return dashboard


def _keep_serving(dashboard) -> None:
    """After the prints: the page keeps showing them (and says the link ended) until Ctrl-C."""
    if dashboard is not None:
        click.echo(f"dashboard still at {dashboard.url}; Ctrl-C stops it", err=True)
        _wait_until_interrupted()


def _wait_until_interrupted() -> None:
    """Sleep until Ctrl-C (KeyboardInterrupt, handled by the caller)."""
    while True:
        time.sleep(1.0)


class ConsoleReadiness:
    """The live console's line when a machine's start-up has settled ("ready to print"),
    its atomizer stopped or started again (a subscriber of the engine's messages)."""

    def __init__(self, echo):
        self.echo = echo
        self.said: dict[str, tuple] = {}  # machine → (ready, atomizer restarts) last said

    def __call__(self, message) -> None:
        """One engine message: a line when a machine's readiness changes."""
        if isinstance(message, FinishedMessage):  # the next print has its own start-up
            self.said.pop(message.machine, None)
            return
        settling = getattr(message, "settling", None)
        if settling is None or getattr(message, "provisional", True):
            return
        name, minute = message.machine, message.time_s / 60
        now = (bool(settling.get("ready")), settling.get("restarts", 0))
        before = self.said.get(name)
        self.said[name] = now
        if before is None:
            said = "ready to print" if now[0] else "waiting for the line to settle"
            self.echo(f"{name}: start-up at {minute:.1f} min — {said}")
        elif now[1] != before[1]:
            self.echo(
                f"{name}: the atomizer started again at {minute:.1f} min: not ready to print "
                "until the line settles"
            )
        elif now[0] and not before[0]:
            self.echo(f"{name}: {settling.get('text', 'ready to print')}")
        elif before[0] and not now[0]:
            self.echo(f"{name} at {minute:.1f} min: {settling.get('text', 'not ready to print')}")


def _follow_parts(engine, publisher, machines, entry: dict, tolerance) -> None:
    """Each machine's live part map, fed by the engine and published to the dashboard."""
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.apps.quality.live_map import LivePartMap
    from ajtwin.engine.part_live import follow_engine
    from ajtwin.engine.print_job import entry_job

    the_job = entry_job(entry)
    for name in machines:
        part = LivePartMap(the_job, tolerance=tolerance)
        publisher.open_part(name, part.header())
        follow_engine(engine, name, part, publisher.publish_part)


def _job(program, process_speed, rapid_speed, tolerance) -> dict | None:
    """The job the machines run (:func:`ajtwin.engine.print_job.job_entry`), read before
    anything connects; None without --job."""
    options = {"process_speed_mm_s": process_speed, "rapid_speed_mm_s": rapid_speed,
               "tolerance": tolerance}  # fmt: skip
    if program is None:
        if any(v is not None for v in options.values()):
            raise click.UsageError("--process-speed, --rapid-speed and --tolerance go with --job")
        return None
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.engine.print_job import job_entry

    try:
        return job_entry(program, **options)
    except ValueError as exc:  # a program that cannot be read
        raise click.ClickException(str(exc)) from None
