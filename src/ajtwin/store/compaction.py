"""Registry compaction: the storage policy and the covariance retention (``machine compact``).

``compact`` re-encodes a machine's arrays with the storage policy
(:mod:`ajtwin.store.arrays`; version-1 prints hold raw ``.npy`` and the whole covariance
sequence), drops the periodic covariance key frames of prints older than
``keep_covariances_days`` (the end covariance, the alarms' covariances, every σ and mean
stay) and VACUUMs the file (switching it to ``auto_vacuum=INCREMENTAL``, as new
registries are, so that later closed live sessions give their pages back). A live
session that ends with its print stored drops its own per-step rows
(``Registry.save_print``); of the machine's *closed* sessions that still hold them
(written by older code, or kept with ``keep_live_steps``) compact drops the per-step
samples and published states (``live_samples``, ``live_states``: the stored print holds
the same samples and states, compressed) and keeps the session row and its alarms; an
open session is left whole, since a restarted ``ajtwin live`` replays it.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from ajtwin.store import arrays as _arrays
from ajtwin.store.connection import rollback_if_open
from ajtwin.store.registry import Registry, RegistryError, printable


def file_bytes(path) -> int:
    """Size of a registry on disk: the file and its WAL."""
    total = 0
    for suffix in ("", "-wal"):
        p = Path(str(path) + suffix)
        if p.exists():
            total += p.stat().st_size
    return total


def checkpointed_bytes(registry: Registry) -> int:
    """Bytes of the registry file after its write-ahead log is checkpointed into it."""
    _checkpoint(registry._conn)
    return int(Path(registry.path).stat().st_size)


def _checkpoint(conn):
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def compact(
    registry: Registry,
    name: str,
    keep_covariances_days: float = 30.0,
    *,
    now: _dt.datetime | None = None,
    vacuum: bool = True,
) -> dict:
    """Apply the storage policy and the covariance retention to machine ``name``.

    Parameters
    ----------
    keep_covariances_days : float
        Prints ingested longer ago than this keep covariances only at their end and
        alarms; younger ones keep the policy's periodic key frames too.
    now : datetime, optional
        "Now" for the retention (tests); default the current UTC time.

    Returns
    -------
    dict: ``bytes_before``, ``bytes_after`` (file + WAL), ``prints``, ``reencoded``
    (version-1 prints converted), ``thinned`` (prints whose key frames were dropped),
    ``live_steps_dropped`` (per-step rows of closed live sessions, module docstring).
    """
    if not keep_covariances_days >= 0:
        raise RegistryError(f"--keep-covariances-days must be ≥ 0, got {keep_covariances_days}")
    machine = registry.machine(name)
    conn = registry._conn
    now = now or _dt.datetime.now(_dt.UTC)
    cutoff = now - _dt.timedelta(days=float(keep_covariances_days))
    _checkpoint(conn)
    before = file_bytes(registry.path)
    prints = conn.execute(
        "SELECT id, seq, ingested_at FROM prints WHERE machine_id = ? ORDER BY seq",
        (machine["id"],),
    ).fetchall()
    reencoded = thinned = 0
    registry.discard_stale_drafts()
    for row in prints:
        _merge_parts(registry, row["id"], row["seq"])
        stored = conn.execute(
            "SELECT name, npy, codec FROM print_arrays WHERE print_id = ?", (row["id"],)
        ).fetchall()
        try:
            ingested = _dt.datetime.fromisoformat(row["ingested_at"])
        except ValueError:
            ingested = now  # unreadable time: keep its key frames
        if ingested.tzinfo is None:
            ingested = ingested.replace(tzinfo=_dt.UTC)
        old = ingested < cutoff
        alarm_times = [
            t
            for r in conn.execute(
                "SELECT detected_s, onset_s FROM anomalies WHERE print_id = ?", (row["id"],)
            )
            for t in (r[0], r[1])
        ]
        decoded = {}
        for r in stored:
            try:
                decoded[r["name"]] = _arrays.decode(r["npy"], r["codec"])
            except ValueError as exc:
                raise RegistryError(
                    f"{registry.path}: registry damaged at print {row['seq']}, array "
                    f"{printable(r['name'])}: {exc}; nothing compacted from there on"
                ) from None
        legacy = any(r["codec"] == _arrays.NPY for r in stored)
        if legacy:
            every = -1.0 if old else None
            encoded = _arrays.encode_all(decoded, registry.policy, alarm_times, every_s=every)
            reencoded += 1
        elif old and "covariance_steps" in decoded:
            steps = decoded["covariance_steps"]
            n = int(decoded["time_s"].shape[0]) if "time_s" in decoded else int(steps.max()) + 1
            keep = _arrays.keyframe_steps(n, decoded.get("time_s"), -1.0, alarm_times)
            mask = np.isin(steps, keep)
            if mask.all():
                continue
            encoded = {
                "covariance_steps": _arrays.encode(steps[mask]),
                "covariance_keyframes": _arrays.encode(decoded["covariance_keyframes"][mask]),
            }
            thinned += 1
        else:
            continue
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.execute("DELETE FROM print_arrays WHERE print_id = ?", (row["id"],))
            for key in decoded:
                if key not in encoded and key not in ("covariances", "predicted_means"):
                    encoded[key] = (
                        next(r["codec"] for r in stored if r["name"] == key),
                        next(r["npy"] for r in stored if r["name"] == key),
                    )
            conn.executemany(
                "INSERT INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
                [(row["id"], key, blob, codec) for key, (codec, blob) in encoded.items()],
            )
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        if old and legacy:
            thinned += 1
    live_steps_dropped = _drop_closed_live_steps(conn, machine["name"], machine["id"])
    if vacuum:
        _checkpoint(conn)
        # from now on the file also shrinks when a live session closes (release_free_pages)
        conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
        conn.execute("VACUUM")
        _checkpoint(conn)
    return {
        "bytes_before": before,
        "bytes_after": file_bytes(registry.path),
        "prints": len(prints),
        "reencoded": reencoded,
        "thinned": thinned,
        "live_steps_dropped": live_steps_dropped,
    }


def _merge_parts(registry: Registry, print_id: int, seq: int) -> None:
    """A print stored in parts (written as it ran) gets one row per array, the parts joined
    exactly (each array keeps its stored type), in one transaction; then the retention
    below treats it as any other print."""
    conn = registry._conn
    rows = conn.execute(
        "SELECT name, codec, blob FROM print_array_parts WHERE print_id = ? ORDER BY name, part",
        (print_id,),
    ).fetchall()
    if not rows:
        return
    parts: dict[str, list] = {}
    for r in rows:
        try:
            parts.setdefault(r["name"], []).append(_arrays.decode(r["blob"], r["codec"]))
        except ValueError as exc:
            raise RegistryError(
                f"{registry.path}: registry damaged at print {seq}, array "
                f"{printable(r['name'])}: {exc}; nothing compacted from there on"
            ) from None
    joined = _arrays.join_parts(parts)
    conn.execute("BEGIN IMMEDIATE")
    try:
        conn.executemany(
            "INSERT OR REPLACE INTO print_arrays (print_id, name, npy, codec) VALUES (?, ?, ?, ?)",
            [(print_id, key, *reversed(_arrays.encode(value))) for key, value in joined.items()],
        )
        conn.execute("DELETE FROM print_array_parts WHERE print_id = ?", (print_id,))
        conn.execute("COMMIT")
    except BaseException:
        rollback_if_open(conn)
        raise


def _drop_closed_live_steps(conn, name: str, machine_id: int) -> int:
    """Per-step rows of the machine's closed live sessions whose print is stored (module
    docstring); returns how many steps were dropped. One transaction."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        sessions = [
            r[0]
            for r in conn.execute(
                "SELECT s.id FROM live_sessions s JOIN prints p ON p.id = s.print_id "
                "WHERE s.machine = ? AND s.status = 'closed' AND p.machine_id = ?",
                (name, machine_id),
            )
        ]
        dropped = 0
        for session_id in sessions:
            dropped += conn.execute(
                "DELETE FROM live_samples WHERE session_id = ?", (session_id,)
            ).rowcount
            conn.execute("DELETE FROM live_states WHERE session_id = ?", (session_id,))
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    return dropped
