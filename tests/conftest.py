import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MPLBACKEND", "Agg")

# `--doctest-modules` (pyproject) is for src/: this file is not a module of examples, and
# importing it as one would clash with src/conftest.py under the same name
collect_ignore = ["conftest.py"]

import contextlib  # noqa: E402
import fcntl  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from store_backends import _ADMIN, BACKENDS, new_schema, on_postgres  # noqa: E402


# ---------------------------------------------------------------------- PostgreSQL
# One PostgreSQL server for the whole test session, shared by the xdist workers: the first
# worker that needs it starts it (initdb + pg_ctl in a folder of the session's base
# temporary folder, 127.0.0.1 on a free port; as root the server runs as the `postgres`
# user, ajtwin.store.pg_cluster); each worker notes itself as a user under a file lock, and
# the last one to finish stops it by its PID. Each test gets a schema of its own in it (a
# fresh, empty registry: the URL's options=-csearch_path=...).
def _shared_folder(tmp_path_factory) -> Path:
    base = tmp_path_factory.getbasetemp()
    # xdist workers' base folders are popen-gwN beside one another
    return base.parent if base.name.startswith("popen-gw") else base


@contextlib.contextmanager
def _locked(folder: Path):
    with open(folder / "postgresql.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def postgres_server(tmp_path_factory):
    """The session's PostgreSQL server (:class:`ajtwin.store.pg_cluster.LocalCluster`)."""
    from ajtwin.store.pg_cluster import LocalCluster, server_binaries

    if server_binaries() is None:
        pytest.fail("PostgreSQL's server is not installed: `make postgresql` installs it")
    shared = _shared_folder(tmp_path_factory)
    state = shared / "postgresql.json"
    with _locked(shared):
        info = json.loads(state.read_text()) if state.exists() else {"users": 0}
        if "folder" not in info:
            # a folder of its own in /tmp: as root the server runs as `postgres`, which may
            # not enter pytest's private base folder
            info["folder"] = tempfile.mkdtemp(prefix="ajtwin-test-pg-")
        cluster = LocalCluster(info["folder"], port=info.get("port"), durable=False)
        if cluster.pid() is None or not _alive(cluster.pid()):
            t0 = time.perf_counter()
            cluster.start()
            info["start_s"] = round(time.perf_counter() - t0, 2)
        cluster.started = True
        info.update(port=cluster.port, users=info["users"] + 1)
        state.write_text(json.dumps(info))
    yield cluster
    with _locked(shared):
        info = json.loads(state.read_text())
        info["users"] -= 1
        if info["users"] <= 0:
            admin = _ADMIN.pop(cluster.port, None)
            if admin is not None:
                admin.close()
            cluster.stop()  # pg_ctl stop, else by the PID of its postmaster.pid
            shutil.rmtree(info.pop("folder"), ignore_errors=True)
            info.pop("port", None)
        state.write_text(json.dumps(info))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(params=BACKENDS)
def store(request, tmp_path):
    """Where a new, empty registry is: an SQLite file's path, or a PostgreSQL URL (a schema
    of its own on the session's server). Tests that take it run on both databases."""
    if request.param == "sqlite":
        return tmp_path / "registry.sqlite"
    return new_schema(request.getfixturevalue("postgres_server"))


@pytest.fixture
def pg_store(request):
    """A new, empty registry on the session's PostgreSQL server (its URL)."""
    return new_schema(request.getfixturevalue("postgres_server"))


@pytest.fixture
def new_store(request, store, tmp_path):
    """A function giving another new, empty registry on the same database as ``store``."""
    made = [0]

    def make():
        made[0] += 1
        if on_postgres(store):
            return new_schema(request.getfixturevalue("postgres_server"))
        return tmp_path / f"registry-{made[0]}.sqlite"

    return make


# ---------------------------------------------------------------- what `make test` says
# (tests/suite_progress.py): long files first, and a line every AJTWIN_TEST_HEARTBEAT
# seconds naming the tests still running
def pytest_collection_modifyitems(session, config, items):
    from suite_progress import CACHE_KEY, known_file_seconds, longest_files_first

    cache = getattr(config, "cache", None)
    # a fresh clone (CI) has no cache: the durations of a measured run kept in the tree
    seconds = {**known_file_seconds(), **(cache.get(CACHE_KEY, {}) if cache is not None else {})}
    if seconds:
        order = longest_files_first([item.nodeid for item in items], seconds)
        items[:] = [items[i] for i in order]


def _controller(config) -> bool:
    return not hasattr(config, "workerinput")  # not an xdist worker


def pytest_configure(config):
    every = os.environ.get("AJTWIN_TEST_HEARTBEAT")
    config._ajtwin_file_seconds = {}
    config._ajtwin_heartbeat = None
    if every and _controller(config):
        from suite_progress import Heartbeat

        def write(line):  # the terminal reporter is registered after this hook may run
            reporter = config.pluginmanager.get_plugin("terminalreporter")
            if reporter is not None:
                reporter.write_line(line)

        config._ajtwin_heartbeat = Heartbeat(float(every), write)
        config._ajtwin_heartbeat.start()


def pytest_runtest_logstart(nodeid, location):
    beat = getattr(_CONFIG.get("config"), "_ajtwin_heartbeat", None)
    if beat is not None:
        beat.started(nodeid)


def pytest_runtest_logreport(report):
    config = _CONFIG.get("config")
    if config is None:
        return
    from suite_progress import file_of

    spent = config._ajtwin_file_seconds
    spent[file_of(report.nodeid)] = spent.get(file_of(report.nodeid), 0.0) + report.duration
    if report.when == "teardown" and config._ajtwin_heartbeat is not None:
        config._ajtwin_heartbeat.finished(report.nodeid)


@pytest.hookimpl(optionalhook=True)  # an xdist hook
def pytest_xdist_node_collection_finished(node, ids):
    beat = getattr(_CONFIG.get("config"), "_ajtwin_heartbeat", None)
    if beat is not None:
        beat.total = len(ids)  # every worker collects the whole suite


def pytest_collection_finish(session):
    beat = getattr(session.config, "_ajtwin_heartbeat", None)
    if beat is not None and not beat.total:
        beat.total = len(session.items)


def pytest_sessionstart(session):
    _CONFIG["config"] = session.config


def pytest_sessionfinish(session, exitstatus):
    config = session.config
    beat = getattr(config, "_ajtwin_heartbeat", None)
    if beat is not None:
        beat.stop()
    cache = getattr(config, "cache", None)
    spent = getattr(config, "_ajtwin_file_seconds", {})
    # recorded from `make test`'s runs only (a run of a few tests would under-count a file)
    if cache is not None and spent and _controller(config) and beat is not None:
        # measured files replace their old figure; the others keep theirs
        from suite_progress import CACHE_KEY

        cache.set(CACHE_KEY, {**cache.get(CACHE_KEY, {}), **spent})


#: the run's config, for the hooks that are not given it
_CONFIG: dict = {}
