"""Who may reach the dashboard: loopback addresses freely, anything wider only with a token.

The checks run before the server listens (``ajtwin dashboard``, ``ajtwin live
--dashboard``, :class:`ajtwin.web.server.BackgroundServer`); a refusal is a
:class:`click.UsageError` whose message proposes a token.
"""

from __future__ import annotations

import ipaddress
import secrets

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
            f"access token with --token (or ${TOKEN_ENV}), e.g. --token "
            f"{secrets.token_urlsafe(16)}"
        )
    if token is not None and len(token) < 8:
        raise click.UsageError("the access token must have at least 8 characters")
