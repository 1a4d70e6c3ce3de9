"""``ajtwin printer serve`` and ``ajtwin live`` (docs/live.md, docs/opcua.md)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from ajtwin.io.cli_options import record_options
from ajtwin.store.cli import open_registry, store_option


def _logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # asyncua logs every request at INFO
    logging.getLogger("asyncua").setLevel(logging.ERROR)


def _users(username, password, user_list) -> dict:
    users = {}
    if username:
        if password is None:
            raise click.UsageError("--username needs --password")
        users[username] = password
    for item in user_list:
        name, sep, pwd = item.partition(":")
        if not sep:
            raise click.UsageError(f"--user {item!r}: expected NAME:PASSWORD")
        users[name] = pwd
    return users


@click.group()
def printer():
    """The virtual printer as a live machine."""


@printer.command("serve")
@click.option("--scenario", default="nozzle_clog", show_default=True, help="Packaged scenario.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--speed", type=float, default=1.0, show_default=True, help="Simulated s per s.")
@click.option("--machines", "n_machines", type=int, default=1, show_default=True)
@click.option("--name", "name_prefix", default="aj300-", show_default=True, help="Name prefix.")
@click.option("--duration-min", type=float, default=None, help="Print length [min].")
@click.option("--fault-onset-min", type=float, default=None, help="Move the fault's onset.")
@click.option("--start-s", type=float, default=0.0, help="Start at this simulated time [s].")
@click.option("--buffer-rows", type=int, default=300, show_default=True, help="SampleBuffer rows.")
@click.option("--endpoint", default="opc.tcp://127.0.0.1:4840", show_default=True)
@click.option("--username", default=None, help="A user (anonymous access is then off).")
@click.option("--password", default=None, envvar="AJTWIN_OPCUA_PASSWORD")
@click.option("--user", "user_list", multiple=True, help="More users as NAME:PASSWORD.")
@click.option("--certificate", type=click.Path(path_type=Path), default=None)
@click.option("--private-key", type=click.Path(path_type=Path), default=None)
@click.option(
    "--generate-certificate",
    is_flag=True,
    help="Create a self-signed --certificate/--private-key if they do not exist.",
)
@click.option(
    "--trust",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder of trusted client certificates (others refused).",
)
@click.option("--verbose", is_flag=True)
def serve(
    scenario,
    seed,
    speed,
    n_machines,
    name_prefix,
    duration_min,
    fault_onset_min,
    start_s,
    buffer_rows,
    endpoint,
    username,
    password,
    user_list,
    certificate,
    private_key,
    generate_certificate,
    trust,
    verbose,
):
    """Serve N virtual printers over OPC UA in real (--speed 1) or accelerated time."""
    import asyncio
    from urllib.parse import urlparse

    from ajtwin.live.printer_server import PrinterServer, VirtualMachine, ensure_certificate

    _logging(verbose)
    if speed <= 0:
        raise click.UsageError("--speed must be positive")
    users = _users(username, password, user_list)
    if (certificate is None) != (private_key is None):
        raise click.UsageError("--certificate and --private-key go together")
    if generate_certificate:
        if certificate is None:
            raise click.UsageError("--generate-certificate needs --certificate and --private-key")
        host = urlparse(endpoint).hostname or "localhost"
        asyncio.run(
            ensure_certificate(certificate, private_key, host, "urn:ajtwin:virtual-printer")
        )
    overrides = None
    if fault_onset_min is not None:
        overrides = {"fault": {"onset_min": float(fault_onset_min)}}
    try:
        machines = [
            VirtualMachine(
                f"{name_prefix}{i + 1:02d}",
                scenario,
                seed=seed + i,
                speed=speed,
                duration_min=duration_min,
                overrides=overrides,
                start_s=start_s,
            )
            for i in range(n_machines)
        ]
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    server = PrinterServer(
        endpoint,
        machines,
        users=users,
        certificate=certificate,
        private_key=private_key,
        trusted=trust,
        buffer_rows=buffer_rows,
    )
    click.echo(
        f"serving {', '.join(m.name for m in machines)} at {endpoint} (x{speed:g}); Ctrl-C stops",
        err=True,
    )
    try:
        asyncio.run(server.serve())
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        raise click.ClickException(f"{endpoint}: {exc}") from None


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
    help="Also serve the browser dashboard from this process on 127.0.0.1:PORT (0: a free port).",
)
@click.option(
    "--transition",
    default="paper",
    show_default=True,
    help="Droplet-size row of the twin: a profile of ajtwin/data/transition.toml "
    "(input_following: d_a follows Q_c/I_A; the engine carries the input response; "
    "docs/forecast.md).",
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
    verbose,
    csv_dialect,
    aliases,
    store,
):
    """Run the live twin beside a machine (OPC UA, or a growing CSV with --follow)."""
    import asyncio

    from ajtwin.live.engine import LiveEngine
    from ajtwin.live.link import LinkRefused, OpcUaLink, follow_csv

    _logging(verbose)
    if (url is None) == (follow is None):
        raise click.UsageError("give exactly one of --opcua URL or --follow FILE")
    if follow is not None and len(machines) != 1:
        raise click.UsageError("--follow follows one --machine")
    from ajtwin.model.droplet_dynamics import transition_profiles

    if transition not in transition_profiles():
        raise click.BadParameter(
            f"no profile {transition!r}; choose one of {', '.join(transition_profiles())}",
            param_hint="--transition",
        )
    registry = open_registry(store, create=True)  # the live twin writes
    engine = LiveEngine(
        registry, twin_overrides=None if transition == "paper" else {"transition": transition}
    )
    engine.warm_up(len(machines))
    out = None
    if messages is not None:
        out = messages.open("a", encoding="utf-8")
        engine.subscribe(lambda m: out.write(json.dumps(m, default=str) + "\n") or out.flush())
    dashboard = None
    if dashboard_port is not None:
        # the dashboard in a thread of this process; every engine message is pushed to it
        from ajtwin.web.publisher import LivePublisher
        from ajtwin.web.server import BackgroundServer

        publisher = LivePublisher()
        engine.subscribe(publisher.publish_engine)
        for name in machines:
            publisher.open_print(name)
        dashboard = BackgroundServer(registry.path, publisher, port=dashboard_port)
        click.echo(f"dashboard: open {dashboard.url}", err=True)
    if generate_certificate:
        from ajtwin.live.printer_server import ensure_certificate

        if certificate is None or private_key is None:
            raise click.UsageError("--generate-certificate needs --certificate and --private-key")
        asyncio.run(
            ensure_certificate(certificate, private_key, "localhost", "urn:ajtwin:live-client")
        )
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
        else:
            link = OpcUaLink(
                url,
                list(machines),
                engine,
                username=username,
                password=password,
                security=security,
                certificate=certificate,
                private_key=private_key,
                server_certificate=server_certificate,
                max_backoff_s=max_backoff,
            )
            asyncio.run(link.run())
            click.echo(f"followed {', '.join(machines)} to the end of their prints")
    except LinkRefused as exc:
        raise click.ClickException(str(exc)) from None
    except (ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    except KeyboardInterrupt:
        click.echo("stopped; the live session stays open and resumes on the next start", err=True)
    finally:
        engine.shutdown()
        if out is not None:
            out.close()
        if dashboard is not None:
            dashboard.stop()
