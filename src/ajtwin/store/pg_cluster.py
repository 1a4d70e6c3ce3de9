"""A PostgreSQL server of one's own in a folder: ``initdb`` + ``pg_ctl`` (tests, benchmarks,
the lab's fault runs).

:class:`LocalCluster` makes a database cluster in a new folder with Debian's server
binaries (``/usr/lib/postgresql/N/bin``, package ``postgresql``; ``make postgresql``
installs it), starts it on 127.0.0.1 at a free port, and stops it by the PID in its
``postmaster.pid``. It is for throwaway servers, nothing listens beyond the loopback.
``durable=False`` (the tests) skips the flushes to disk (``initdb -N``, ``fsync=off``):
a killed server or client still keeps every commit (it is in the operating system's
cache), only a crash of the computer would not; ``durable=True`` (benchmarks, the fault
runs) flushes every commit as a production server does.

PostgreSQL refuses to run as root (``initdb: cannot be run as root``). Run as root, the
cluster's folder is given to the ``postgres`` user (made by Debian's package) and every
server command runs as that user through ``runuser -u postgres --`` (util-linux; it
changes user without a login shell or a password, which ``su`` would want); run as any
other user, the commands run as that user.

Roles made on start: ``ajtwin`` (superuser, trusted on 127.0.0.1: the tests' own),
``ajtwin_secret`` (needs its password, SCRAM: the password-file paths) and
``ajtwin_reader`` (password-less, granted reading only: the dashboard's role).

Example
-------
::

    with LocalCluster() as cluster:
        url = cluster.url("ajtwin")          # postgresql://ajtwin@127.0.0.1:PORT/ajtwin
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

#: the password of the ``ajtwin_secret`` role (a throwaway server on the loopback)
SECRET_PASSWORD = "lab-secret-42"


def server_binaries() -> Path | None:
    """The folder of Debian's newest PostgreSQL server binaries, or None (not installed)."""
    found = sorted(
        glob.glob("/usr/lib/postgresql/*/bin/initdb"),
        key=lambda p: int(Path(p).parts[-3]) if Path(p).parts[-3].isdigit() else 0,
    )
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return None if initdb is None else Path(initdb).resolve().parent


def free_port() -> int:
    """A TCP port of 127.0.0.1 free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalCluster:
    """A PostgreSQL server in a new folder (module docstring); a context manager.

    Parameters
    ----------
    folder : path, optional
        Where the cluster goes (a new temporary folder by default, removed on close). As
        root it must be a folder the ``postgres`` user can reach (not under a private
        folder such as pytest's ``/tmp/pytest-of-root``).
    port : int, optional
        TCP port on 127.0.0.1 (default: a free one).
    durable : bool
        Flush commits to disk (module docstring).
    host : str
        The address it listens on (127.0.0.1; another when it runs in ``netns``).
    netns : str, optional
        A network namespace (``ip netns``) the server runs in: the lab's fault runs cut
        its network (:mod:`ajtwin.studies.lab_faults`).
    """

    def __init__(
        self,
        folder=None,
        port: int | None = None,
        durable: bool = True,
        host: str = "127.0.0.1",
        netns: str | None = None,
    ):
        self.durable = bool(durable)
        self.host = str(host)
        self.netns = netns
        self.bin = server_binaries()
        if self.bin is None:
            raise RuntimeError(
                "PostgreSQL's server is not installed (Debian package 'postgresql'); "
                "`make postgresql` installs it"
            )
        self._own_folder = folder is None
        self.folder = Path(folder or tempfile.mkdtemp(prefix="ajtwin-pg-"))
        self.data = self.folder / "data"
        self.socket_dir = self.folder / "socket"
        self.port = int(port or free_port())
        self.log_file = self.folder / "server.log"
        self._user = "postgres" if os.geteuid() == 0 else None
        self.started = False

    # ------------------------------------------------------------------ running commands
    def _run(self, *args, check=True, timeout=120) -> subprocess.CompletedProcess:
        command = [str(a) for a in args]
        if self._user is not None:
            command = ["runuser", "-u", self._user, "--", *command]
        if self.netns is not None:
            command = ["ip", "netns", "exec", self.netns, *command]
        done = subprocess.run(
            command, capture_output=True, text=True, check=False, timeout=timeout, cwd="/"
        )
        if check and done.returncode != 0:
            said = (done.stderr or done.stdout).strip()[-600:]
            raise RuntimeError(f"{Path(str(args[0])).name} failed: {said}")
        return done

    def _give_folder(self) -> None:
        if self._user is None:
            return
        entry = pwd.getpwnam(self._user)
        for path in [self.folder, *self.folder.rglob("*")]:
            os.chown(path, entry.pw_uid, entry.pw_gid)

    # ------------------------------------------------------------------ life
    def start(self) -> LocalCluster:
        """initdb (first time), start the server, wait until it answers, make the roles."""
        self.socket_dir.mkdir(parents=True, exist_ok=True)
        fresh = not (self.data / "PG_VERSION").exists()
        self._give_folder()
        if fresh:
            self._run(
                self.bin / "initdb", "-D", self.data, "-U", "postgres", "--auth-local=trust",
                "--auth-host=scram-sha-256", "-E", "UTF8", "--locale=C.UTF-8",
                *([] if self.durable else ["--no-sync"]),
            )  # fmt: skip
            hba = self.data / "pg_hba.conf"
            # the secret role needs its password; the others are trusted on the loopback
            hba.write_text(
                "local all all trust\n"
                "host all ajtwin_secret 127.0.0.1/32 scram-sha-256\n"
                "host all ajtwin_secret samenet scram-sha-256\n"
                "host all all 127.0.0.1/32 trust\n"
                "host all all samenet trust\n"
            )
            self._give_folder()
        self.restart()
        try:
            if fresh:
                self.psql(
                    "postgres",
                    "CREATE ROLE ajtwin SUPERUSER LOGIN; "
                    f"CREATE ROLE ajtwin_secret SUPERUSER LOGIN PASSWORD '{SECRET_PASSWORD}'; "
                    "CREATE ROLE ajtwin_reader LOGIN",
                )
                self.psql("postgres", "CREATE DATABASE ajtwin OWNER ajtwin")
        except BaseException:
            self.close()
            raise
        return self

    def restart(self) -> None:
        """Start the server (again) on the same port and data; waits until it answers."""
        options = (
            f"-c listen_addresses={self.host} -p {self.port} -k {self.socket_dir} "
            "-c max_connections=200 -c shared_buffers=64MB"
            + ("" if self.durable else " -c fsync=off -c full_page_writes=off")
        )
        self._run(
            self.bin / "pg_ctl", "-D", self.data, "-l", self.log_file, "-o", options,
            "-w", "-t", "60", "start",
        )  # fmt: skip
        self.started = True
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if self._run(self.bin / "pg_isready", "-h", self.host, "-p", self.port,
                         check=False).returncode == 0:  # fmt: skip
                return
            time.sleep(0.1)
        raise RuntimeError(f"PostgreSQL did not answer on port {self.port}; see {self.log_file}")

    def pid(self) -> int | None:
        """The server's PID (its ``postmaster.pid``), None when it is not running."""
        try:
            return int((self.data / "postmaster.pid").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return None

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (``pg_ctl stop -m MODE``; if that fails, SIGTERM then SIGKILL to
        its PID), leaving the folder."""
        if not self.started:
            return
        pid = self.pid()
        done = self._run(
            self.bin / "pg_ctl", "-D", self.data, "-m", mode, "-w", "-t", "30", "stop",
            check=False,
        )  # fmt: skip
        if done.returncode != 0 and pid is not None:
            for sig in (15, 9):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, sig)
                for _ in range(50):
                    try:
                        os.kill(pid, 0)
                    except ProcessLookupError:
                        break
                    time.sleep(0.1)
        self.started = False

    def close(self) -> None:
        """Stop the server and remove a folder this object made."""
        self.stop()
        if self._own_folder:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> LocalCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ use
    def url(self, database: str = "ajtwin", user: str = "ajtwin", **params) -> str:
        """The libpq URL of ``database`` as ``user`` over TCP (``params``: query string)."""
        query = "&".join(f"{k}={v}" for k, v in params.items())
        return f"postgresql://{user}@{self.host}:{self.port}/{database}" + (
            f"?{query}" if query else ""
        )

    def psql(self, database: str, sql: str) -> str:
        """Run ``sql`` with psql as the ``postgres`` superuser over the unix socket."""
        done = self._run(
            self.bin / "psql", "-X", "-q", "-v", "ON_ERROR_STOP=1", "-h", self.socket_dir,
            "-p", self.port, "-U", "postgres", "-d", database, "-At", "-c", sql,
        )  # fmt: skip
        return done.stdout
