"""Who may reach the dashboard: loopback addresses freely, anything wider only with a token.

The token is given in ``$AJTWIN_DASHBOARD_TOKEN`` or a file (``--token-file``): any user of
the computer can read a command line (``ps``), so ``--token`` still works but is warned
about. The checks run before the server listens (``ajtwin dashboard``, ``ajtwin live
--dashboard``, :class:`ajtwin.web.server.BackgroundServer`); a refusal is a
:class:`click.UsageError` whose message proposes a token.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
import stat
from pathlib import Path

import click

TOKEN_ENV = "AJTWIN_DASHBOARD_TOKEN"


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``.

    >>> is_loopback("127.0.0.1"), is_loopback("localhost"), is_loopback("0.0.0.0")
    (True, True, False)
    """
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_access(host: str, token: str | None) -> None:
    """Refuse to serve beyond this computer without a token (click.UsageError)."""
    if not is_loopback(host) and not token:
        raise click.UsageError(
            f"serving on {host} makes the dashboard reachable from other computers: give an "
            f"access token with --token-file FILE or in ${TOKEN_ENV} (--token also works but "
            f"shows it to every user in ps), e.g. export {TOKEN_ENV}="
            f"{secrets.token_urlsafe(16)}"
        )
    if token is not None and len(token) < 8:
        raise click.UsageError("the access token must have at least 8 characters")


#: the warning ``--token`` on the command line gets
COMMAND_LINE_TOKEN_WARNING = (
    "warning: --token on the command line is visible to every user of this computer (ps, "
    f"/proc); give the token in ${TOKEN_ENV} or in a file with --token-file instead"
)


def read_token_file(path) -> str:
    """The access token kept in ``path`` (its first line, stripped; click.UsageError when the
    file is unreadable or holds no token). A file other users may read is refused: the token
    would then be no secret."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise click.UsageError(f"--token-file {path}: cannot read it ({exc})") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise click.UsageError(
            f"--token-file {path}: other users may read it (mode {stat.S_IMODE(mode):o}); "
            f"make it private with `chmod 600 {path}`"
        )
    lines = text.strip().splitlines()
    token = lines[0].strip() if lines else ""
    if not token:
        raise click.UsageError(f"--token-file {path}: the file holds no token (first line empty)")
    return token


def dashboard_token(token: str | None, token_file, from_command_line: bool) -> str | None:
    """The access token from ``--token``/``$AJTWIN_DASHBOARD_TOKEN`` or ``--token-file``
    (not both); a token typed on the command line gets :data:`COMMAND_LINE_TOKEN_WARNING`
    on stderr."""
    if token_file is not None:
        if token is not None:
            raise click.UsageError(
                f"give the token once: --token-file or --token/${TOKEN_ENV}, not both"
            )
        return read_token_file(token_file)
    if token is not None and from_command_line:
        click.echo(COMMAND_LINE_TOKEN_WARNING, err=True)
    return token
