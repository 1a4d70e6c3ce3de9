"""What the store tests share about the registry's two databases (the fixtures that start
the PostgreSQL server are in ``conftest.py``)."""

from __future__ import annotations

import uuid

import pytest

#: the registry's two databases; every store test runs on both (the ``store`` fixture)
BACKENDS = ("sqlite", "postgresql")
#: a superuser connection to the test run's server, per worker (makes the tests' schemas)
_ADMIN: dict = {}


def new_schema(cluster) -> str:
    """A new empty schema in the server's ``ajtwin`` database; the URL of a registry in it."""
    import psycopg

    conn = _ADMIN.get(cluster.port)
    if conn is None or conn.closed or conn.broken:
        conn = _ADMIN[cluster.port] = psycopg.connect(cluster.url(), autocommit=True)
    schema = "t_" + uuid.uuid4().hex[:16]
    conn.execute(f"CREATE SCHEMA {schema}")
    return cluster.url("ajtwin", options=f"-csearch_path%3D{schema}")


def on_postgres(store) -> bool:
    """Whether a ``store`` fixture value is a PostgreSQL URL."""
    return str(store).startswith("postgresql://")


#: a store test whose PostgreSQL run is long (subprocesses, the twin): `make test-all`
#: runs it; the default suite keeps its SQLite run
SLOW_ON_POSTGRES = pytest.param("postgresql", marks=pytest.mark.slow)
