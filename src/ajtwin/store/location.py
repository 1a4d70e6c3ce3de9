"""Where a registry is: an SQLite file or a PostgreSQL database, from ``--store``.

``--store`` (or ``$AJTWIN_STORE``) is either a path (an SQLite file, the embedded default)
or a PostgreSQL URL in libpq's form::

    --store ~/lab/registry.sqlite
    --store sqlite:///srv/ajtwin/registry.sqlite
    --store postgresql://twin@server.lab:5432/ajtwin?sslmode=verify-full

Any other scheme (``mysql://``, ``postgres+psycopg://``, ``http://`` …) is refused with a
sentence naming it, never taken for a file name. The password is never part of the
store: a URL that holds one is refused, and libpq finds it as it always does
(``$PGPASSWORD``, ``~/.pgpass`` or the URL's ``passfile=``), or ``--store-password-file``
(``$AJTWIN_STORE_PASSWORD_FILE``) names a file whose first line is the password, read
each time a connection is made and never shown. Every other URL parameter (``sslmode``,
``sslrootcert``, ``connect_timeout``, ``options=-csearch_path=lab1`` …) goes to libpq as
given.

Example
-------
>>> parse_store("postgresql://twin@db.lab/ajtwin?sslmode=verify-full").kind
'postgresql'
>>> str(parse_store("sqlite:///tmp/r.sqlite"))
'/tmp/r.sqlite'
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlsplit

from ajtwin.store.connection import RegistryError

SQLITE = "sqlite"
POSTGRESQL = "postgresql"
#: URL schemes of a PostgreSQL registry (libpq accepts both)
POSTGRESQL_SCHEMES = ("postgresql", "postgres")
#: environment variable naming the password file (``--store-password-file``)
PASSWORD_FILE_ENV = "AJTWIN_STORE_PASSWORD_FILE"

# a scheme as RFC 3986 spells it, then "://" ("C:\\x" or "a:b" are paths)
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.\-]*)://")


@dataclass(frozen=True)
class StoreLocation:
    """A registry's place: ``kind`` (:data:`SQLITE` or :data:`POSTGRESQL`), the file
    ``path`` of an SQLite registry, or the password-free libpq ``url`` of a PostgreSQL one
    with the ``password_file`` its connections read (None: libpq's own ways).

    ``str()`` is what messages show: the path, or the URL (which holds no password).
    """

    kind: str
    path: Path | None = None
    url: str | None = None
    password_file: Path | None = None

    def __str__(self) -> str:
        return str(self.path) if self.kind == SQLITE else str(self.url)

    @property
    def is_sqlite(self) -> bool:
        """Whether the registry is an SQLite file."""
        return self.kind == SQLITE

    def password(self) -> str | None:
        """The password of :attr:`password_file` (its first line), read now; None without
        one. A missing or unreadable file is a :class:`RegistryError` naming it."""
        if self.password_file is None:
            return None
        try:
            text = Path(self.password_file).read_text(encoding="utf-8")
        except OSError as exc:
            raise RegistryError(
                f"--store-password-file {self.password_file}: cannot be read ({exc.strerror}); "
                "give a readable file holding the database password on its first line"
            ) from None
        lines = text.splitlines()
        return lines[0] if lines else ""


def default_file() -> Path:
    """``$XDG_DATA_HOME/ajtwin/registry.sqlite``, else ``~/.local/share/ajtwin/registry.sqlite``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / "ajtwin" / "registry.sqlite"


def parse_store(value=None, password_file=None) -> StoreLocation:
    """The :class:`StoreLocation` of ``--store`` ``value`` (a path, ``sqlite:///PATH`` or a
    PostgreSQL URL; None: ``$AJTWIN_STORE``, else the default file).

    ``password_file``: ``--store-password-file`` (None: ``$AJTWIN_STORE_PASSWORD_FILE`` if
    set). Refused with a :class:`RegistryError` that says why: an unknown URL scheme, a
    URL with a password in it, a password file for an SQLite registry.
    """
    if isinstance(value, StoreLocation):
        if password_file is None:
            return value
        return StoreLocation(value.kind, value.path, value.url, Path(password_file))
    if value is None:
        value = os.environ.get("AJTWIN_STORE") or None
    if password_file is None:
        password_file = os.environ.get(PASSWORD_FILE_ENV) or None
    if value is None:
        location = StoreLocation(SQLITE, path=default_file())
    else:
        location = _parse(os.fspath(value) if isinstance(value, os.PathLike) else str(value))
    if password_file is not None:
        if location.is_sqlite:
            raise RegistryError(
                f"--store-password-file is for a PostgreSQL registry; {location.path} is an "
                "SQLite file (no password)"
            )
        location = StoreLocation(location.kind, url=location.url, password_file=Path(password_file))
    return location


def _parse(text: str) -> StoreLocation:
    match = _SCHEME.match(text)
    if match is None:
        return StoreLocation(SQLITE, path=Path(text).expanduser())
    scheme = match.group(1).lower()
    if scheme == SQLITE:
        rest = text[match.end() :]
        if not rest.startswith("/"):
            raise RegistryError(
                f"--store {text}: an SQLite URL names an absolute path (sqlite:///srv/r.sqlite); "
                "or give the file's path itself"
            )
        return StoreLocation(SQLITE, path=Path(unquote(rest)))
    if scheme not in POSTGRESQL_SCHEMES:
        raise RegistryError(
            f"--store {_without_password(text)}: ajtwin cannot keep a registry in a "
            f"{scheme!r} database; give an SQLite file's path, or a PostgreSQL URL "
            "(postgresql://user@host:5432/dbname)"
        )
    parts = urlsplit(text)
    if parts.password is not None or re.search(r"(^|[?&])password=", parts.query):
        raise RegistryError(
            f"--store {_without_password(text)}: the URL holds a password, which would show on "
            "the command line, in logs and on pages; remove it and let libpq find it "
            "($PGPASSWORD, ~/.pgpass or passfile=) or give --store-password-file FILE"
        )
    return StoreLocation(POSTGRESQL, url=text)


def _without_password(text: str) -> str:
    """``text`` with a URL's password (user:PASSWORD@ or password=…) replaced by ***."""
    text = re.sub(r"(://[^/@:]*):[^/@]*@", r"\1:***@", text)
    return re.sub(r"([?&]password=)[^&]*", r"\1***", text)
