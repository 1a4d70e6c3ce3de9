"""``ajtwin printer serve``: the virtual printer as a live OPC UA machine
(docs/reference/opcua.md)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from urllib.parse import urlparse

import click

from ajtwin.cli.options import configure_logging, job_speeds, process_speed_option


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


def _print_id(given: str | None, i: int, n_machines: int) -> dict:
    """The ``print_id`` keyword of machine ``i`` ({}: a new id of its own)."""
    if given is None:
        return {}
    return {"print_id": given if n_machines == 1 else f"{given}-{i + 1}"}


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
@click.option(
    "--wait-for-client",
    is_flag=True,
    help="Hold the prints at their start until a client (ajtwin live) subscribes: it misses "
    "nothing of them.",
)
@click.option(
    "--print-id",
    default=None,
    help="The PrintId served (default: a new one each start; with --start-s, give the "
    "stopped server's to continue its print rather than begin a new one).",
)
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
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="A machine program (.prg) every printer runs, looped to the print's length "
    "(the camera trails the nozzle: no line while nothing is printed or seen).",
)
@process_speed_option
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
    wait_for_client,
    print_id,
    endpoint,
    username,
    password,
    user_list,
    certificate,
    private_key,
    generate_certificate,
    trust,
    program,
    process_speed,
    verbose,
):
    """Serve N virtual printers over OPC UA in real (--speed 1) or accelerated time."""

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.live.printer_server import PrinterServer, VirtualMachine, ensure_certificate
    from ajtwin.simulation.job_print import read_job

    configure_logging(verbose)
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
    if process_speed is not None and program is None:
        raise click.UsageError("--process-speed goes with --job")
    overrides = None
    if fault_onset_min is not None:
        overrides = {"fault": {"onset_min": float(fault_onset_min)}}
    try:
        if program is not None:
            speeds = job_speeds(process_speed)
            program, _ = read_job(program, speeds["process_speed_mm_s"], None,
                                  speeds["speed_schedule"])  # fmt: skip
        machines = [
            VirtualMachine(
                f"{name_prefix}{i + 1:02d}",
                scenario,
                seed=seed + i,
                speed=speed,
                duration_min=duration_min,
                overrides=overrides,
                start_s=start_s,
                job=program,
                **_print_id(print_id, i, n_machines),
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
        wait_for_client=wait_for_client,
    )
    held = "; the prints start when a client subscribes" if wait_for_client else ""
    click.echo(
        f"serving {', '.join(m.name for m in machines)} at {endpoint} (x{speed:g}){held}; "
        "Ctrl-C stops",
        err=True,
    )
    try:
        asyncio.run(server.serve())
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        raise click.ClickException(f"{endpoint}: {exc}") from None
