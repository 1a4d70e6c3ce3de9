"""The registry when its file or disk fails: read-only, full, damaged. Every failure is a
sentence naming the file and what to do, said before the work where it can be; nothing is
read from a damaged file in silence, no read-only journal file is left behind."""

from __future__ import annotations

import os
import shutil
import sqlite3
import stat
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

import ajtwin.store.connection as C
from ajtwin.cli import main
from ajtwin.io.records import write_record
from ajtwin.simulation import simulate
from ajtwin.store.registry import Registry, RegistryError
from test_web_data import hand_print

# root ignores file modes unless it gives up the capabilities that let it
_AS_USER = (
    ["setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner"]
    if os.geteuid() == 0
    else []
)
needs_modes = pytest.mark.skipif(
    os.geteuid() == 0 and shutil.which("setpriv") is None,
    reason="running as root without setpriv: file modes cannot be enforced",
)


def _cli(*args, cwd=None, timeout=180):
    """``ajtwin ARGS`` in a fresh process that file modes bind (root without DAC override)."""
    cmd = [*_AS_USER, sys.executable, "-m", "ajtwin.cli", *map(str, args)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env)


@pytest.fixture(scope="module")
def short_print(tmp_path_factory):
    path = tmp_path_factory.mktemp("failures") / "p.parquet"
    write_record(simulate("exp1", seed=1, duration_min=2), path)
    return path


def _store(tmp_path, prints=1):
    path = tmp_path / "r.sqlite"
    reg = Registry(path)
    reg.add_machine("M")
    for k in range(prints):
        hand_print(reg, "M", seq_before=k or None, tag=str(k))
    reg.close()
    return path


# ------------------------------------------------------------------ read-only
@needs_modes
def test_a_read_only_registry_is_refused_before_the_twin_runs(tmp_path, short_print):
    store = _store(tmp_path)
    store.chmod(0o444)
    res = _cli("ingest", "--machine", "M", "--store", store, short_print, "--no-progress")
    assert res.returncode == 1, res.stderr
    assert "the registry cannot be written (Permission denied)" in res.stderr
    assert "nothing was run" in res.stderr and "Traceback" not in res.stderr
    assert "ingested" not in res.stdout  # refused before the twin, not after it
    res = _cli("machine", "add", "N", "--store", store)
    assert res.returncode == 1 and "cannot be written" in res.stderr
    # reading still works, and leaves no journal file its owner cannot write
    res = _cli("machine", "history", "M", "--store", store)
    assert res.returncode == 0, res.stderr
    for suffix in ("-wal", "-shm"):
        journal = store.with_name(store.name + suffix)
        if journal.exists():
            assert journal.stat().st_mode & stat.S_IWUSR, suffix
    # made writable again, it works at once
    store.chmod(0o644)
    res = _cli("machine", "add", "N", "--store", store)
    assert res.returncode == 0, res.stderr
    reg = Registry(store, create=False)
    assert reg.machine("N")["name"] == "N" and reg.machine("M")["n_prints"] == 1


@needs_modes
def test_a_read_only_folder_is_refused_before_the_work(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    store = _store(folder)
    folder.chmod(0o555)
    try:
        res = _cli("machine", "add", "N", "--store", store)
    finally:
        folder.chmod(0o755)
    assert res.returncode == 1
    assert "the registry's folder cannot be written (Permission denied)" in res.stderr


def test_journal_files_created_read_only_get_their_owners_write_permission(tmp_path):
    store = _store(tmp_path)
    shm = store.with_name(store.name + "-shm")
    shm.write_bytes(b"")
    shm.chmod(0o444)
    reg = Registry(store, create=False)  # SQLite keeps the -shm while a connection is open
    assert shm.stat().st_mode & stat.S_IWUSR
    reg.close()


# ------------------------------------------------------------------ disk full
def small_disk(monkeypatch, store):
    """From now on, ``store`` may grow by at most 2 pages: SQLite's 'database or disk is
    full' (SQLITE_FULL) on every connection, as on a full disk."""
    real = C.connect
    conn = sqlite3.connect(store)
    limit = conn.execute("PRAGMA page_count").fetchone()[0] + 2
    conn.close()

    def connect(path, timeout_s=30.0):
        conn = real(path, timeout_s)
        conn.execute(f"PRAGMA max_page_count = {limit}")
        return conn

    monkeypatch.setattr(C, "connect", connect)
    monkeypatch.setattr("ajtwin.store.database.connect", connect)


def test_a_full_disk_is_a_sentence_in_every_command_that_writes(tmp_path, short_print, monkeypatch):
    store = _store(tmp_path)
    small_disk(monkeypatch, store)
    runner = CliRunner()
    res = runner.invoke(
        main, ["ingest", "--machine", "M", "--store", str(store), str(short_print), "--no-progress"]
    )
    assert res.exit_code == 1, res.output
    assert "the disk holding it is full (database or disk is full)" in res.output
    assert "nothing of this command was stored" in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)
    # a machine with many names: the machines table outgrows the two pages
    for k in range(200):
        res = runner.invoke(main, ["machine", "add", f"machine-{k:03d}-" + "x" * 80,
                                   "--store", str(store)])  # fmt: skip
        if res.exit_code:
            break
    assert res.exit_code == 1 and "the disk holding it is full" in res.output, res.output
    assert not isinstance(res.exception, sqlite3.Error)
    reg = Registry(store, create=False)
    assert reg.machine("M")["n_prints"] == 1  # the refused ingest left the registry as it was


def test_a_second_rollback_does_not_hide_the_full_disk(tmp_path):
    store = _store(tmp_path)
    conn = C.connect(store)
    conn.execute("BEGIN IMMEDIATE")
    conn.execute("ROLLBACK")  # as SQLite does itself on SQLITE_FULL
    C.rollback_if_open(conn)  # no 'cannot rollback - no transaction is active'
    conn.close()


# ------------------------------------------------------------------ damaged files
def _damage_page(path, page: int):
    size = 4096
    data = bytearray(path.read_bytes())
    data[page * size : page * size + 16] = b"\xa5" * 16  # a b-tree page header
    path.write_bytes(bytes(data))


def _damage_schema(path):
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA writable_schema = ON")
    conn.execute("UPDATE sqlite_master SET sql = 'CREATE TABLE prints (id REFERANCES !' "
                 "WHERE name = 'prints'")  # fmt: skip
    conn.commit()
    conn.close()


def _damage_text(path):
    conn = sqlite3.connect(path)
    conn.execute("UPDATE prints SET summary_json = CAST(x'7b22ff22' AS TEXT)")
    conn.commit()
    conn.close()


READERS = (["machine", "show", "M"], ["machine", "history", "M"], ["machine", "list"])


@pytest.mark.parametrize(
    "damage, commands",
    # flipped bytes in a text value leave a valid page: found when the value is read
    [("page", READERS), ("schema", READERS), ("text", READERS[:1])],
)
def test_a_damaged_registry_is_refused_by_every_command(tmp_path, damage, commands):
    store = _store(tmp_path, prints=3)
    conn = sqlite3.connect(store)
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    conn.close()
    if damage == "page":
        _damage_page(store, pages - 2)
    elif damage == "schema":
        _damage_schema(store)
    else:
        _damage_text(store)
    runner = CliRunner()
    for args in commands:
        res = runner.invoke(main, [*args, "--store", str(store)])
        assert res.exit_code == 1, (damage, args, res.output)
        assert f"{store}: registry damaged" in res.output, (damage, args, res.output)
        assert "restore it from a backup" in res.output
        assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    with pytest.raises(RegistryError, match="registry damaged"):
        Registry(store, create=False).last_print("M")


def test_an_index_that_lost_a_row_is_found_on_open(tmp_path):
    """A lookup through a damaged index misses rows in silence: the full check finds it."""
    store = _store(tmp_path, prints=2)
    conn = sqlite3.connect(store)
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    index_root = conn.execute(
        "SELECT rootpage FROM sqlite_master WHERE name = 'sqlite_autoindex_print_arrays_1'"
    ).fetchone()[0]
    conn.close()
    data = bytearray(store.read_bytes())
    start = (index_root - 1) * 4096
    cells = data[start + 8 : start + 4096]
    # flip a byte inside the index's first record payload (past the page's cell pointers)
    tail = start + 4096 - 60
    data[tail] ^= 0x08
    assert cells  # the page exists
    store.write_bytes(bytes(data))
    with pytest.raises(RegistryError, match="registry damaged .SQLite's integrity check"):
        Registry(store, create=False)


def test_the_check_runs_once_per_process_and_version_of_the_file(tmp_path, monkeypatch):
    store = _store(tmp_path)
    calls = []
    real = C.Connection.execute

    def execute(self, sql, parameters=()):
        if "integrity_check" in sql or "quick_check" in sql:
            calls.append(sql)
        return real(self, sql, parameters)

    monkeypatch.setattr(C.Connection, "execute", execute)
    C._CHECKED.clear()
    for _ in range(3):
        Registry(store, create=False).close()
    assert calls == ["PRAGMA integrity_check"]
    assert np.isfinite(C.FULL_CHECK_MAX_BYTES)
