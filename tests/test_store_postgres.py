"""A registry on PostgreSQL: the store URL, passwords, roles, TLS, foreign schemas, one
writer per machine, a server restart under a live twin. What the SQLite file's tests pin
for a file (tests/test_store_failures.py) pinned here for a server."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time

import numpy as np
import psycopg
import pytest
from click.testing import CliRunner

from ajtwin.cli import main
from ajtwin.store.location import parse_store
from ajtwin.store.pg_cluster import SECRET_PASSWORD, LocalCluster
from ajtwin.store.registry import Registry, RegistryError
from store_backends import new_schema


def _cli(*args, env=None):
    return CliRunner().invoke(main, [str(a) for a in args], env=env)


def _schema_of(url: str) -> str:
    return url.rsplit("search_path%3D", 1)[1]


def _admin(cluster):
    return psycopg.connect(cluster.url(), autocommit=True)


# ---------------------------------------------------------------------- the store URL
@pytest.mark.parametrize(
    "url, scheme",
    [
        ("mysql://twin@db.lab/ajtwin", "mysql"),
        ("postgres+psycopg://twin@db.lab/ajtwin", "postgres+psycopg"),
        ("http://db.lab/ajtwin", "http"),
        ("sqlserver://db.lab", "sqlserver"),
    ],
)
def test_a_store_url_of_another_database_is_refused_naming_its_scheme(
    tmp_path, monkeypatch, url, scheme
):
    monkeypatch.chdir(tmp_path)
    res = _cli("machine", "add", "m1", "--store", url)
    assert res.exit_code == 2, res.output
    assert f"cannot keep a registry in a {scheme!r} database" in res.output
    assert list(tmp_path.iterdir()) == []  # no folder named "mysql:" made for a file


def test_a_password_in_the_url_is_refused_and_never_shown(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for url in ("postgresql://twin:s3cr3t@db.lab/ajtwin", "postgresql://db.lab/a?password=s3cr3t"):
        res = _cli("machine", "list", "--store", url)
        assert res.exit_code == 2 and "holds a password" in res.output, res.output
        assert "s3cr3t" not in res.output
    assert parse_store("sqlite:///srv/r.sqlite").path.as_posix() == "/srv/r.sqlite"
    with pytest.raises(RegistryError, match="--store-password-file is for a PostgreSQL"):
        parse_store(tmp_path / "r.sqlite", tmp_path / "pw")


def test_the_password_file_opens_a_role_that_needs_one(postgres_server, pg_store, tmp_path):
    url = pg_store.replace("postgresql://ajtwin@", "postgresql://ajtwin_secret@")
    res = _cli("machine", "add", "m1", "--store", url)
    assert res.exit_code == 1 and "the server refused the login" in res.output, res.output
    assert "--store-password-file" in res.output
    secret = tmp_path / "pw"
    secret.write_text(SECRET_PASSWORD + "\n")
    secret.chmod(0o600)
    res = _cli("machine", "add", "m1", "--store", url, "--store-password-file", secret)
    assert res.exit_code == 0, res.output
    env = {"AJTWIN_STORE": url, "AJTWIN_STORE_PASSWORD_FILE": str(secret)}
    res = _cli("machine", "show", "m1", env=env)
    assert res.exit_code == 0 and "machine m1" in res.output
    assert SECRET_PASSWORD not in res.output
    # libpq's own ways work as well: $PGPASSWORD
    res = _cli("machine", "list", "--store", url, env={"PGPASSWORD": SECRET_PASSWORD})
    assert res.exit_code == 0 and "m1" in res.output
    res = _cli("machine", "list", "--store", url, "--store-password-file", tmp_path / "none")
    assert res.exit_code == 1 and "cannot be read" in res.output


def test_tls_options_reach_libpq(pg_store):
    # this server has no TLS: libpq refuses as asked, and says so
    res = _cli("machine", "list", "--store", pg_store + "&sslmode=require")
    assert res.exit_code == 1 and "SSL" in res.output, res.output


# ---------------------------------------------------------------------- roles and schemas
def test_a_read_only_role_serves_the_dashboard_and_is_refused_writes(postgres_server, pg_store):
    from ajtwin.engine.views import RegistryView

    owner = Registry(pg_store)
    owner.add_machine("lab1")
    owner.close()
    schema = _schema_of(pg_store)
    with _admin(postgres_server) as conn:  # the grants of the how-to
        conn.execute(f"GRANT USAGE ON SCHEMA {schema} TO ajtwin_reader")
        conn.execute(f"GRANT SELECT ON ALL TABLES IN SCHEMA {schema} TO ajtwin_reader")
    reader = pg_store.replace("postgresql://ajtwin@", "postgresql://ajtwin_reader@")
    view = RegistryView(reader)
    assert [m["name"] for m in view.fleet()] == ["lab1"]
    view.close()
    assert _cli("machine", "show", "lab1", "--store", reader).exit_code == 0
    res = _cli("machine", "add", "lab2", "--store", reader)
    assert res.exit_code == 1 and "role 'ajtwin_reader' may not write" in res.output, res.output
    res = _cli("ingest", "--machine", "lab1", __file__, "--store", reader)
    assert res.exit_code == 1 and "may not write" in res.output, res.output


def test_a_schema_of_other_tables_is_refused_untouched(postgres_server, pg_store):
    schema = _schema_of(pg_store)
    with _admin(postgres_server) as conn:
        conn.execute(f"CREATE TABLE {schema}.customers (id integer)")
    res = _cli("machine", "add", "Z", "--store", pg_store)
    assert res.exit_code == 1 and "not an ajtwin registry (tables: customers)" in res.output
    with _admin(postgres_server) as conn:
        tables = conn.execute(
            "SELECT table_name FROM information_schema.tables WHERE table_schema = %s", (schema,)
        ).fetchall()
    assert tables == [("customers",)]


def test_read_only_commands_never_create_a_registry_in_an_empty_schema(postgres_server, pg_store):
    for args in (["machine", "list"], ["machine", "show", "M"], ["machine", "history", "M"]):
        res = _cli(*args, "--store", pg_store)
        assert res.exit_code == 1 and "no registry in" in res.output, res.output
    with _admin(postgres_server) as conn:
        n = conn.execute(
            "SELECT COUNT(*) FROM information_schema.tables WHERE table_schema = %s",
            (_schema_of(pg_store),),
        ).fetchone()[0]
    assert n == 0
    assert _cli("machine", "add", "M", "--store", pg_store).exit_code == 0


# ---------------------------------------------------------------------- one writer a machine
def test_a_second_twin_of_the_same_machine_on_another_host_is_refused(pg_store, caplog):
    from ajtwin.store.live_log import LiveLog

    reg = Registry(pg_store)
    reg.add_machine("aj1")
    heard = time.time() - 5
    reg._db.execute(  # the claim a twin on the PC "bay-2" holds, heard 5 s ago
        "INSERT INTO machine_writers VALUES ('aj1', 'bay-2', 4242, 'ajtwin live', ?, ?)",
        (heard, heard),
    )
    log = LiveLog(pg_store)
    with pytest.raises(RegistryError, match="being written by ajtwin live on host bay-2"):
        log.open_session_of("aj1")
    assert reg.live_sessions("aj1") == []  # nothing interleaved
    # a claim not heard from for longer than it lasts is taken over
    reg._db.execute("UPDATE machine_writers SET heard_unix = ?", (time.time() - 3600,))
    assert log.open_session_of("aj1") is None
    assert reg.machine_writer("aj1")["host"] == socket.gethostname()
    # the first twin, back, is told its machine was taken over; it writes nothing
    sid = log.open_session("aj1", source="t", start=None, theta=np.zeros(5))
    reg._db.execute("UPDATE machine_writers SET host = 'bay-2'")
    with caplog.at_level(logging.ERROR, logger="ajtwin.store"):
        log.append(sid, [(0, 0.0, np.ones(3), np.ones(5), {"step": 0})], [])
    assert "taken over by ajtwin live on host bay-2" in caplog.text
    assert reg.live_n_steps(sid) == 0


WRITER = """
import numpy as np
from ajtwin.store.registry import NewPrint, Registry
reg = Registry({url!r})
entry = NewPrint(content_hash={name!r}, source="t", meta={{}}, summary={{}}, n_samples=1,
                 duration_s=1.0, start_mean=np.ones(5), start_cov=np.eye(5),
                 end_mean=np.ones(5), end_cov=np.eye(5), theta_before=np.zeros(5),
                 theta_after=np.zeros(5))
reg.save_print("m", entry, expected_last_seq=1)
"""


def test_two_writers_of_one_machine_one_wins_the_other_is_told(pg_store):
    from test_store import _fake_print

    reg = Registry(pg_store)
    reg.add_machine("m")
    _fake_print(reg, "m", "first", None)
    env = dict(os.environ, AJTWIN_STORE_TEST_SLEEP_IN_TRANSACTION="1.5")
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                WRITER.format(tests=os.path.dirname(__file__), url=pg_store, name=name),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for name in ("second-a", "second-b")
    ]
    outcomes = [p.communicate(timeout=120) + (p.returncode,) for p in procs]
    assert sorted(rc for _, _, rc in outcomes) == [0, 1], outcomes
    loser = next(err for _, err, rc in outcomes if rc)
    assert "got print 2 while this ingest ran from print 1; ingest again" in loser
    assert [p["seq"] for p in reg.history("m").to_dict("records")] == [1, 2]


# ---------------------------------------------------------------------- the server away
@pytest.fixture
def own_server():
    """A PostgreSQL server of this test's own (it is stopped and started again)."""
    with LocalCluster(durable=False) as cluster:
        yield cluster


def test_a_live_twin_rides_out_a_server_restart_and_loses_nothing(own_server, caplog):
    from ajtwin.engine.fleet import LiveEngine
    from ajtwin.estimation.samples import Sample
    from ajtwin.simulation import simulate

    url = new_schema(own_server)
    rec = simulate("exp1", seed=2, duration_min=3.0)
    reg = Registry(url)
    engine = LiveEngine(reg, asynchronous=False, commit_every_s=0)
    engine.log.registry.outbox.retry_every_s = 0.5
    reg.outbox.retry_every_s = 0.5

    def feed(a, b):
        for k in range(a, b):
            engine.feed("aj1", Sample(rec.time_s[k], rec.inputs[k], rec.outputs[k]))

    feed(0, 60)
    caplog.set_level(logging.INFO, logger="ajtwin.store")
    own_server.stop(mode="immediate")  # the server goes away mid-print
    feed(60, 120)  # the twin goes on; its writes wait
    assert len(engine.log.registry.outbox) > 0
    assert "the database server cannot be reached" in caplog.text
    own_server.restart()
    feed(120, len(rec))
    print_id = engine.close("aj1")
    engine.shutdown()
    engine.log.close()
    assert "kept writes stored" in caplog.text
    with Registry(url) as after:
        stored = after.print_arrays(print_id)
        session = after.live_sessions("aj1")[0]
    assert np.array_equal(stored["time_s"], rec.time_s)  # every sample, once
    assert np.array_equal(stored["inputs"], rec.inputs)
    assert session["status"] == "closed" and session["print_id"] == print_id
    reg.close()
