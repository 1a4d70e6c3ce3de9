"""Registry compaction: the storage policy and the covariance retention (``machine compact``).

``compact`` re-encodes a machine's arrays with the storage policy
(:mod:`ajtwin.store.arrays`; version-1 prints hold raw ``.npy`` and the whole covariance
sequence), drops the periodic covariance key frames of prints older than
``keep_covariances_days`` (the end covariance, the alarms' covariances, every σ and mean
stay) and gives the space back (an SQLite file is VACUUMed and switched to
``auto_vacuum=INCREMENTAL``, as new registries are, so that later closed live sessions
give their pages back; PostgreSQL's tables are VACUUMed). A live
session that ends with its print stored drops its own per-step rows
(``Registry.save_print``); of the machine's *closed* sessions that still hold them
(written by older code, or kept with ``keep_live_steps``) compact drops the per-step
samples and published states (``live_samples``, ``live_states``: the stored print holds
the same samples and states, compressed) and keeps the session row and its alarms; an
open session is left whole, since a restarted ``ajtwin live`` replays it.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from ajtwin.store import arrays as _arrays
from ajtwin.store.registry import Registry, RegistryError, printable


def file_bytes(registry: Registry) -> int:
    """Size of a registry: an SQLite file and its WAL, or its tables on the server."""
    return registry.size_bytes()


def checkpointed_bytes(registry: Registry) -> int:
    """Bytes of the registry once an SQLite file's write-ahead log is moved into it."""
    return registry.checkpointed_bytes()


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
    dict: ``bytes_before``, ``bytes_after`` (:func:`file_bytes`), ``prints``, ``reencoded``
    (version-1 prints converted), ``thinned`` (prints whose key frames were dropped),
    ``live_steps_dropped`` (per-step rows of closed live sessions, module docstring).
    """
    if not keep_covariances_days >= 0:
        raise RegistryError(f"--keep-covariances-days must be ≥ 0, got {keep_covariances_days}")
    registry.machine(name)
    now = now or _dt.datetime.now(_dt.UTC)
    cutoff = now - _dt.timedelta(days=float(keep_covariances_days))
    before = registry.checkpointed_bytes()
    prints = registry.print_rows(name)
    reencoded = thinned = 0
    registry.discard_stale_drafts()
    for row in prints:
        _merge_parts(registry, row["id"], row["seq"])
        stored = registry.stored_arrays(row["id"])
        try:
            ingested = _dt.datetime.fromisoformat(row["ingested_at"])
        except ValueError:
            ingested = now  # unreadable time: keep its key frames
        if ingested.tzinfo is None:
            ingested = ingested.replace(tzinfo=_dt.UTC)
        old = ingested < cutoff
        alarm_times = registry.alarm_times(row["id"])
        decoded = {}
        for r in stored:
            try:
                decoded[r["name"]] = _arrays.decode(r["blob"], r["codec"])
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
        kept = {r["name"]: (r["codec"], r["blob"]) for r in stored}
        for key in decoded:
            if key not in encoded and key not in ("covariances", "predicted_means"):
                encoded[key] = kept[key]
        registry.rewrite_arrays(row["id"], encoded)
        if old and legacy:
            thinned += 1
    live_steps_dropped = registry.drop_closed_live_steps(name)
    if vacuum:
        registry.compact_storage()
    return {
        "bytes_before": before,
        "bytes_after": registry.size_bytes(),
        "prints": len(prints),
        "reencoded": reencoded,
        "thinned": thinned,
        "live_steps_dropped": live_steps_dropped,
    }


def _merge_parts(registry: Registry, print_id: int, seq: int) -> None:
    """A print stored in parts (written as it ran) gets one row per array, the parts joined
    exactly (each array keeps its stored type), in one transaction; then the retention
    below treats it as any other print."""
    rows = registry.stored_arrays(print_id, parts=True)
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
    registry.rewrite_arrays(
        print_id, {key: _arrays.encode(value) for key, value in joined.items()}, from_parts=True
    )
