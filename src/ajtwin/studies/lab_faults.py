"""A lab on one PostgreSQL registry, and the faults it must ride out (real processes).

:func:`run_lab` sets up what a lab with several printers runs — served virtual printers
(``ajtwin printer serve``, the printers), one ``ajtwin live`` per printer (each printer's
PC), an ``ajtwin ingest`` of a finished print and ``ajtwin dashboard`` on a read-only role
(the server), all on one PostgreSQL server — then, while the printers print, makes the
faults of docs/howto/lab-with-several-printers.md happen:

* ``kill``: ``kill -9`` of one twin mid-print; it is started again 3 s later (a PC
  rebooted) and resumes its open session from the registry;
* ``second_host``: a twin on another host (a UTS namespace with its own host name,
  ``unshare --uts``) given a machine name already being written: it must be refused;
* ``restart``: PostgreSQL stopped and started again mid-print (``pg_ctl stop -m fast``);
* ``network``: the network to the server lost for ``outage_s`` (the server runs in a
  network namespace of its own, reached over a veth pair; a ``blackhole`` route to it
  drops every packet silently, as a pulled cable does).

Then it counts, against the served printers: every machine has exactly one stored print
of ``minutes`` × 60 samples, at the printer's seconds 0, 1, …, each once; every live
session closed with its print; the ingested print stored once (and a second ingest of
the same file refused as a duplicate); the dashboard showed each machine live. The
network fault needs root (namespaces and routes); without it that fault is skipped and
the result says so.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np

from ajtwin.io.records import write_record
from ajtwin.simulation import simulate
from ajtwin.store.pg_cluster import LocalCluster, free_port
from ajtwin.store.registry import Registry

MACHINES = ("aj300-01", "aj300-02", "aj300-03")
INGESTED = "aj-bench"
FAULTS = ("kill", "second_host", "restart", "network")


class NetworkNamespace:
    """A network namespace holding the database server, reached from this host over a veth
    pair (10.231.N.0/30); :meth:`cut` drops every packet to it, :meth:`mend` lets them
    through again. Needs root."""

    def __init__(self):
        tag = f"{os.getpid() % 10000:04d}{random.randrange(100):02d}"
        self.name = f"ajtwin-db-{tag}"
        self.host_if, self.inner_if = f"ajh{tag}", f"ajn{tag}"
        net = random.randrange(1, 250)
        self.host_ip, self.server_ip = f"10.231.{net}.1", f"10.231.{net}.2"
        self._route = f"{self.server_ip}/32"
        steps = [
            ["ip", "netns", "add", self.name],
            ["ip", "link", "add", self.host_if, "type", "veth", "peer", "name", self.inner_if],
            ["ip", "link", "set", self.inner_if, "netns", self.name],
            ["ip", "addr", "add", f"{self.host_ip}/30", "dev", self.host_if],
            ["ip", "link", "set", self.host_if, "up"],
            ["ip", "netns", "exec", self.name, "ip", "addr", "add", f"{self.server_ip}/30",
             "dev", self.inner_if],
            ["ip", "netns", "exec", self.name, "ip", "link", "set", self.inner_if, "up"],
            ["ip", "netns", "exec", self.name, "ip", "link", "set", "lo", "up"],
        ]  # fmt: skip
        try:
            for step in steps:
                subprocess.run(step, check=True, capture_output=True, timeout=30)
        except BaseException:
            self.delete()
            raise

    def cut(self) -> None:
        """Lose the network to the server: its packets are dropped without a word."""
        subprocess.run(["ip", "route", "add", "blackhole", self._route], check=True, timeout=30)

    def mend(self) -> None:
        """The network is back."""
        subprocess.run(["ip", "route", "del", "blackhole", self._route], capture_output=True,
                       check=False, timeout=30)  # fmt: skip

    def delete(self) -> None:
        """Remove the namespace and its link."""
        self.mend()
        subprocess.run(["ip", "link", "del", self.host_if], capture_output=True, timeout=30)
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True, timeout=30)


def _ajtwin(args, log: Path, prefix=()) -> subprocess.Popen:
    return subprocess.Popen(
        [*prefix, sys.executable, "-m", "ajtwin.cli", *map(str, args)],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        env=dict(os.environ),
    )


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM) -> None:
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(proc.pid, sig)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


def _wait(predicate, timeout_s: float, what: str, every_s: float = 0.5):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(every_s)
    raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}")


def _steps(path: Path) -> int:
    if not path.exists():
        return 0
    return sum('"step"' in line and '"provisional": true' not in line for line in path.open())


def _live_on_dashboard(port: int) -> set:
    """Machines the dashboard's fleet page shows printing live now."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/fleet", timeout=5) as r:
            fleet = json.loads(r.read())
    except (OSError, ValueError):
        return set()
    entries = fleet if isinstance(fleet, list) else fleet.get("machines", [])
    return {e["name"] for e in entries if (e.get("live") or {}).get("printing")}


def run_lab(folder, *, minutes: float = 6.0, speed: float = 10.0, faults=FAULTS,
            outage_s: float = 120.0, restart_s: float = 10.0, ingest_minutes: float = 20.0,
            log=print) -> dict:  # fmt: skip
    """Run the lab (module docstring) in ``folder``; the counts and what each fault did.

    Parameters
    ----------
    minutes : float
        The printers' print length [simulated min] (one sample a simulated second).
    speed : float
        Simulated seconds per second.
    faults : tuple of str
        Which of :data:`FAULTS` to make happen.
    outage_s : float
        How long the network to the server is lost [s].
    restart_s : float
        How long PostgreSQL is down when restarted [s].
    ingest_minutes : float
        Length of the print ingested meanwhile [min].
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    faults = tuple(faults)
    report: dict = {"minutes": minutes, "speed": speed, "faults": {}}
    root = os.geteuid() == 0
    ns = NetworkNamespace() if root else None
    if not root:
        report["faults"]["network"] = "skipped: needs root (network namespace, route)"
        faults = tuple(f for f in faults if f != "network")
    cluster = LocalCluster(folder / "postgresql", durable=True,
                           host=ns.server_ip if ns else "127.0.0.1",
                           netns=ns.name if ns else None)  # fmt: skip
    procs: list = []
    try:
        cluster.start()
        url = cluster.url("ajtwin")
        reader = cluster.url("ajtwin", user="ajtwin_reader")
        record = folder / "finished.parquet"
        write_record(simulate("exp1", seed=9, duration_min=ingest_minutes), record)
        with Registry(url) as reg:
            for name in (*MACHINES, INGESTED):
                reg.add_machine(name)
        cluster.psql("ajtwin", "GRANT USAGE ON SCHEMA public TO ajtwin_reader; "
                     "GRANT SELECT ON ALL TABLES IN SCHEMA public TO ajtwin_reader")  # fmt: skip
        endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
        printers = _ajtwin(["printer", "serve", "--machines", len(MACHINES), "--speed", speed,
                            "--duration-min", minutes, "--fault-onset-min", minutes / 2,
                            "--buffer-rows", 4000, "--endpoint", endpoint],
                           folder / "printers.log")  # fmt: skip
        procs.append(printers)
        twins = {}

        def start_twin(name, n, prefix=()):
            proc = _ajtwin(["live", "--machine", name, "--opcua", endpoint, "--store", url,
                            "--messages", folder / f"{name}-{n}.jsonl", "--max-backoff", 1],
                           folder / f"live-{name}-{n}.log", prefix)  # fmt: skip
            procs.append(proc)
            return proc

        for name in MACHINES:
            twins[name] = start_twin(name, 1)
        # a finished print ingested meanwhile, its twin running through the faults
        ingest = _ajtwin(["ingest", "--machine", INGESTED, record, "--store", url,
                          "--no-progress"], folder / "ingest.log")  # fmt: skip
        procs.append(ingest)
        port = free_port()
        dashboard = _ajtwin(["dashboard", "--store", reader, "--port", port],
                            folder / "dashboard.log")  # fmt: skip
        procs.append(dashboard)
        seen_live: set = set()
        t_print = minutes * 60.0 / speed  # wall seconds of the print
        t0 = time.monotonic()

        def started():
            for proc, what in ((printers, "printers"), *((p, f"live-{m}-1") for m, p in
                                                         twins.items())):  # fmt: skip
                if proc.poll() is not None:
                    raise RuntimeError(
                        f"{what} ended early: {(folder / f'{what}.log').read_text()}"
                    )
            return all(_steps(folder / f"{m}-1.jsonl") > 0 for m in MACHINES)

        _wait(started, 600, "every twin's first step")
        t_started = time.monotonic()
        report["twins_started_s"] = round(t_started - t0, 1)
        if t_started > t0 + 0.5 * t_print:
            raise RuntimeError(
                f"the twins took {t_started - t0:.0f} s to start, more than half the print "
                f"({t_print:.0f} s at x{speed:g}): give longer prints (--minutes) or a lower speed"
            )

        def watch(until_s):
            while time.monotonic() < until_s:
                seen_live.update(_live_on_dashboard(port))
                time.sleep(1.0)

        def at(fraction):
            # the faults are spread over the part of the print the twins follow live
            watch(t_started + fraction * (t0 + t_print - t_started))

        if "kill" in faults:
            at(0.2)
            victim = MACHINES[1]
            os.kill(twins[victim].pid, signal.SIGKILL)
            twins[victim].wait(timeout=30)
            time.sleep(3.0)
            twins[victim] = start_twin(victim, 2)
            report["faults"]["kill"] = f"kill -9 of the twin of {victim}, started again 3 s later"
        if "second_host" in faults:
            at(0.3)
            other = _ajtwin(["live", "--machine", MACHINES[0], "--opcua", endpoint,
                             "--store", url, "--max-backoff", 1], folder / "second-host.log",
                            ["unshare", "--uts", "sh", "-c",
                             'hostname bay-9 && exec "$0" "$@"'] if root else ())  # fmt: skip
            procs.append(other)
            other.wait(timeout=300)
            said = (folder / "second-host.log").read_text()
            report["faults"]["second_host"] = {
                "exit_code": other.returncode,
                "refused": "two twins may not write one machine" in said,
                "host": "bay-9" if root else "this host (not root: no UTS namespace)",
            }
        if "restart" in faults:
            at(0.45)
            cluster.stop(mode="fast")
            time.sleep(restart_s)
            cluster.restart()
            report["faults"]["restart"] = f"PostgreSQL stopped for {restart_s:g} s mid-print"
        if "network" in faults:
            at(0.6)
            ns.cut()
            time.sleep(outage_s)
            ns.mend()
            report["faults"]["network"] = f"network to the server lost for {outage_s:g} s"
        for name, proc in twins.items():
            deadline = time.monotonic() + 900
            while proc.poll() is None and time.monotonic() < deadline:
                seen_live.update(_live_on_dashboard(port))
                time.sleep(1.0)
            if proc.returncode != 0:
                raise RuntimeError(f"the twin of {name} ended with {proc.returncode}: see "
                                   f"{folder}/live-{name}-*.log")  # fmt: skip
        ingest.wait(timeout=900)
        again = subprocess.run([sys.executable, "-m", "ajtwin.cli", "ingest", "--machine",
                                INGESTED, str(record), "--store", url, "--no-progress"],
                               capture_output=True, text=True, timeout=600)  # fmt: skip
        report["second_ingest_refused"] = "already ingested" in again.stdout + again.stderr
        report["ingest_exit_code"] = ingest.returncode
        report["dashboard_showed_live"] = sorted(seen_live & set(MACHINES))
        report["wall_s"] = round(time.monotonic() - t0, 1)
        report.update(count(url, minutes))
        report["logged"] = {
            "unreachable": sum("cannot be reached" in p.read_text() for p in
                               folder.glob("live-*.log")),
            "reached_again": sum("kept writes stored" in p.read_text() for p in
                                 folder.glob("live-*.log")),
        }  # fmt: skip
    finally:
        for proc in reversed(procs):
            _stop(proc)
        cluster.close()
        if ns is not None:
            ns.delete()
    log(json.dumps(report, indent=1))
    return report


def count(url: str, minutes: float) -> dict:
    """What the registry holds of each machine's print, against the printers' seconds."""
    n = int(round(minutes * 60))
    out: dict = {"machines": {}}
    with Registry(url) as reg:
        for name in MACHINES:
            history = reg.history(name)
            entry = {"prints": len(history)}
            if len(history):
                arrays = reg.print_arrays(int(history["print_id"].iloc[0]))
                t = np.asarray(arrays["time_s"], dtype=float)
                entry["samples"] = int(len(t))
                entry["missing"] = int(len(set(range(n)) - set(np.round(t).astype(int))))
                entry["duplicated"] = int(len(t) - len(set(np.round(t).astype(int))))
                entry["status"] = history["status"].iloc[0]
            sessions = reg.live_sessions(name)
            entry["sessions"] = [s["status"] for s in sessions]
            out["machines"][name] = entry
        out["ingested_prints"] = len(reg.history(INGESTED))
    out["expected_samples"] = n
    out["lost_or_duplicated"] = sum(
        e.get("missing", n) + e.get("duplicated", 0) for e in out["machines"].values()
    ) + sum(abs(e["prints"] - 1) * n for e in out["machines"].values())
    return out


if __name__ == "__main__":  # pragma: no cover - run by hand: python -m ajtwin.studies.lab_faults
    import argparse

    parser = argparse.ArgumentParser(description="The lab's fault runs on one PostgreSQL.")
    parser.add_argument("folder")
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--speed", type=float, default=5.0)
    parser.add_argument("--outage-s", type=float, default=120.0)
    parser.add_argument("--faults", default=",".join(FAULTS))
    a = parser.parse_args()
    run_lab(a.folder, minutes=a.minutes, speed=a.speed, outage_s=a.outage_s,
            faults=a.faults.split(","))  # fmt: skip
