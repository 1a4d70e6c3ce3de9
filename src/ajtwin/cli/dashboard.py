"""``ajtwin dashboard``: serve the browser dashboard on a machine registry."""

from __future__ import annotations

import os
from pathlib import Path

import click

from ajtwin.cli.options import ToleranceType, store_option
from ajtwin.store.registry import RegistryError
from ajtwin.web.access import TOKEN_ENV, check_access, dashboard_token


@click.command()
@store_option
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("--port", type=int, default=8050, show_default=True, help="Port to listen on.")
@click.option(
    "--token",
    default=None,
    envvar=TOKEN_ENV,
    help=f"Access token every request must carry (required beyond 127.0.0.1). Prefer "
    f"${TOKEN_ENV} or --token-file: a command line is visible to every user (ps).",
)
@click.option(
    "--token-file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="File whose first line is the access token (private: mode 600).",
)
@click.option(
    "--virtual-print",
    "virtual_scenario",
    default=None,
    metavar="SCENARIO",
    help="Also stream a live print of the virtual printer through the twin "
    "(e.g. nozzle_clog), as `ajtwin live` will.",
)
@click.option(
    "--virtual-machine", default="virtual-1", show_default=True, help="Name of the virtual machine."
)
@click.option("--virtual-seed", type=int, default=1, show_default=True, hidden=True)
@click.option(
    "--virtual-minutes", type=float, default=8.0, show_default=True, help="Virtual print length."
)
@click.option(
    "--virtual-onset",
    type=float,
    default=3.0,
    show_default=True,
    help="Fault onset of the virtual print [min].",
)
@click.option(
    "--virtual-rate",
    type=float,
    default=10.0,
    show_default=True,
    help="Virtual-print samples per second (1 = real time).",
)
@click.option(
    "--job",
    "program",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="With --virtual-print: the virtual printer runs this machine program (.prg, looped "
    "to the print's length) and the machine page shows its part map filling in.",
)
@click.option(
    "--tolerance",
    type=ToleranceType(),
    default=None,
    help="With --job: the part's linewidth tolerance in µm (45±3, 45+-3, 42:48).",
)
@click.option(
    "--virtual-wait",
    type=float,
    default=0.0,
    show_default=True,
    hidden=True,
    help="Hold the virtual print until a page is open (at most this many seconds).",
)
def dashboard(
    store,
    host,
    port,
    token,
    token_file,
    virtual_scenario,
    virtual_machine,
    virtual_seed,
    virtual_minutes,
    virtual_onset,
    virtual_rate,
    program,
    tolerance,
    virtual_wait,
):
    """Serve the browser dashboard: the fleet, each machine (live), what-if and advice.

    Bound to 127.0.0.1 by default; any other address needs --token. Open the printed
    address in a browser; every script is served by this process (no internet needed).
    """

    source = click.get_current_context().get_parameter_source("token")
    token = dashboard_token(token, token_file, source == click.core.ParameterSource.COMMANDLINE)
    check_access(host, token)
    if (program is not None or tolerance is not None) and not virtual_scenario:
        raise click.UsageError("--job and --tolerance go with --virtual-print SCENARIO")
    if tolerance is not None and program is None:
        raise click.UsageError("--tolerance goes with --job")
    path = store  # an SQLite file or a PostgreSQL location
    # lazy CLI loading: imported when the command runs, not for --help
    import uvicorn

    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.web.app import create_app
    from ajtwin.web.publisher import LivePublisher

    publisher = LivePublisher()
    feeds = []
    if virtual_scenario:
        # lazy CLI loading: imported when the command runs, not for --help
        from ajtwin.engine.replay import VirtualPrintFeed
        from ajtwin.simulation import load_scenario

        try:
            has_fault = load_scenario(virtual_scenario).fault_kind != "none"
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise click.BadParameter(str(exc), param_hint="--virtual-print") from None
        if has_fault and not 0 <= virtual_onset < virtual_minutes:
            raise click.BadParameter(
                f"the fault onset {virtual_onset:g} min must lie within the "
                f"{virtual_minutes:g}-min print",
                param_hint="--virtual-onset",
            )

        feeds.append(
            VirtualPrintFeed(
                publisher,
                virtual_machine,
                virtual_scenario,
                seed=virtual_seed,
                minutes=virtual_minutes,
                onset_min=virtual_onset,
                rate_hz=virtual_rate,
                wait_for_viewer_s=virtual_wait,
                job=program,
                tolerance=tolerance,
            )
        )
    try:
        app = create_app(path, token=token, publisher=publisher, feeds=feeds)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    url = f"http://{shown}:{port}/" + (f"?token={token}" if token else "")
    click.echo(f"ajtwin dashboard on {path}: open {url}  (Ctrl-C stops it)", err=True)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.web.websocket import SERVER_OPTIONS

    uvicorn.run(app, host=host, port=port, log_level="warning", **SERVER_OPTIONS)
