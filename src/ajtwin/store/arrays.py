"""How a print's per-second arrays are stored: the registry's storage policy and codecs.

A print-hour of raw ``.npy`` blobs cost ~1.9 MB, 57 % of it the full 5×5 covariance of
every second. The policy keeps what later commands need and drops what they do not:

* **exact** (float64 / int, lossless): the raw samples (``measurements``, ``inputs``,
  ``time_s``), θ per step and θ history, ``n_measured``, the guard's firings;
* **float32** (7 significant digits, far below any σ; the print row keeps the end state
  exactly): the states' ``means`` and ``stds``, ``predicted_outputs``,
  ``innovation_variances``, ``nis`` and the filter's state corrections
  x̂_k − x̂_{k|k−1} (``predicted_means`` is rebuilt from the means and corrections, so the
  corrections the detectors sum keep their relative precision);
* **covariances**: the full P_k only at key frames — every ``covariance_every_s`` seconds,
  the print's last step and the steps of alarms (detection and onset) — as
  ``covariance_keyframes`` (K, 5, 5) with ``covariance_steps`` (K,). The print row keeps
  the end covariance (the next print's start, the forecast's start) exactly, and σ_k is
  stored for every step (the detectors use only P_k's diagonal).

Every blob is byte-shuffled and zlib-compressed (codec ``zs1``); version-1 registries hold
plain ``.npy`` blobs (codec ``npy``), which stay readable and which ``machine compact``
re-encodes. Decoding never unpickles: only numeric and boolean dtypes are accepted, and
sizes are checked before anything is allocated.

Example
-------
>>> import numpy as np
>>> codec, blob = encode(np.arange(6.0).reshape(2, 3))
>>> decode(blob, codec).tolist()
[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

NPY = "npy"
ZSHUF = "zs1"
_MAGIC = b"AJZ1"
_KINDS = "fiub"  # float, signed/unsigned int, bool: nothing that can hold an object
_MAX_BYTES = 2**33  # 8 GiB: a blob claiming more is damaged


@dataclass(frozen=True)
class StoragePolicy:
    """What the registry keeps of a print's arrays (see the module docstring).

    Attributes
    ----------
    covariance_every_s : float
        Spacing of the covariance key frames [s]; 0 keeps the whole P_k sequence.
    float32 : tuple of str
        Arrays stored as float32.
    """

    covariance_every_s: float = 60.0
    float32: tuple = (
        "means",
        "stds",
        "predicted_outputs",
        "innovation_variances",
        "nis",
        "state_corrections",
    )


def _uint(dtype) -> np.dtype:
    return np.dtype(f"<u{dtype.itemsize}")


def _pack(a: np.ndarray, delta: bool) -> bytes:
    """Column-major, optionally delta-coded (on the integer view, exactly reversible),
    byte-shuffled, zlib-compressed bytes of ``a``."""
    cols = int(np.prod(a.shape[1:], dtype=np.int64)) if a.ndim > 1 else 1
    table = a.reshape(a.shape[0] if a.ndim else 1, cols)
    if delta:
        table = table.view(_uint(a.dtype))
        table = np.concatenate([table[:1], np.diff(table, axis=0)])  # wraps modulo 2^bits
    raw = np.frombuffer(np.ascontiguousarray(table.T).tobytes(), np.uint8)
    if a.dtype.itemsize > 1 and raw.size:
        # byte-shuffle: high bytes of neighbouring values are alike and compress well
        raw = raw.reshape(-1, a.dtype.itemsize).T
    return zlib.compress(np.ascontiguousarray(raw).tobytes(), 6)


def encode(array, dtype=None) -> tuple[str, bytes]:
    """(codec, blob) of ``array`` (cast to ``dtype`` first if given), lossless for its dtype.

    Floats are stored as they are or delta-coded over time (axis 0), whichever is
    smaller: smooth series (σ, innovation variances) shrink by a third delta-coded.
    """
    a = np.asarray(array, dtype=dtype)
    a = a if a.flags.c_contiguous else a.copy(order="C")  # (ascontiguousarray makes 0-d 1-d)
    if a.dtype.kind not in _KINDS:
        raise ValueError(f"cannot store a {a.dtype} array (numeric or boolean only)")
    a = a.astype(a.dtype.newbyteorder("<"), copy=False)
    payload, delta = _pack(a, False), False
    if a.dtype.kind in "fiu" and a.ndim and a.shape[0] > 2:
        other = _pack(a, True)
        if len(other) < len(payload):
            payload, delta = other, True
    header = json.dumps({"dtype": a.dtype.str, "shape": list(a.shape), "delta": delta}).encode()
    return ZSHUF, _MAGIC + struct.pack("<H", len(header)) + header + payload


def decode(blob, codec: str = ZSHUF) -> np.ndarray:
    """The array in ``blob``; ValueError (never a pickle, never a huge allocation) if the
    blob is damaged or holds anything but a numeric array."""
    if not isinstance(blob, bytes | bytearray | memoryview):
        raise ValueError(f"expected a binary blob, got {type(blob).__name__}")
    blob = bytes(blob)
    if codec == NPY:
        try:
            a = np.load(io.BytesIO(blob), allow_pickle=False)
        except Exception as exc:  # numpy raises ValueError, EOFError, OSError, ...
            raise ValueError(f"not a numeric .npy array ({type(exc).__name__}: {exc})") from None
        if not isinstance(a, np.ndarray) or a.dtype.kind not in _KINDS:
            raise ValueError(f"holds a {getattr(a, 'dtype', type(a))} array, not numbers")
        return a
    if codec != ZSHUF:
        raise ValueError(f"unknown array codec {codec!r}")
    if len(blob) < 6 or not blob.startswith(_MAGIC):
        raise ValueError("not an ajtwin array blob (bad magic)")
    (n_header,) = struct.unpack("<H", blob[4:6])
    try:
        header = json.loads(blob[6 : 6 + n_header])
        dtype = np.dtype(str(header["dtype"]))
        shape = tuple(int(v) for v in header["shape"])
        delta = bool(header.get("delta", False))
    except Exception as exc:
        raise ValueError(f"unreadable array header ({exc})") from None
    if dtype.kind not in _KINDS or dtype.hasobject or any(v < 0 for v in shape):
        raise ValueError(f"holds a {dtype} {shape} array, not numbers")
    n_bytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    if n_bytes > _MAX_BYTES:
        raise ValueError(f"claims {n_bytes} bytes")
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(blob[6 + n_header :], n_bytes + 1)
    except zlib.error as exc:
        raise ValueError(f"compressed data damaged ({exc})") from None
    if len(raw) != n_bytes or inflater.unconsumed_tail:
        raise ValueError(f"{len(raw)} bytes of data for a {dtype} {shape} array")
    if not inflater.eof:  # the stream's end (and its checksum) is missing
        raise ValueError("compressed data damaged (cut short)")
    data = np.frombuffer(raw, np.uint8)
    if dtype.itemsize > 1 and data.size:
        data = data.reshape(dtype.itemsize, -1).T
    rows = shape[0] if shape else 1
    cols = int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
    stored = _uint(dtype) if delta else dtype
    table = np.frombuffer(np.ascontiguousarray(data).tobytes(), stored).reshape(cols, rows).T
    if delta:
        table = np.cumsum(table, axis=0, dtype=stored)  # undoes the wrapped differences
    return np.ascontiguousarray(table).view(dtype).reshape(shape).copy()


def keyframe_steps(
    n_steps: int,
    time_s,
    every_s: float,
    alarm_times=(),
    *,
    origin_s: float | None = None,
    after_s: float | None = None,
    keep_last: bool = True,
) -> np.ndarray:
    """Steps whose full covariance is kept: every ``every_s``, the last, and alarms.

    ``every_s`` ≤ 0 keeps only the last step and the alarm steps. A part of a print (steps
    written as they are produced) passes the print's start ``origin_s``, the time of the
    step before the part ``after_s`` and ``keep_last`` only for the print's last part: the
    steps kept are then the ones the whole print would keep (the first step at or after
    each mark) that lie in the part.
    """
    t = np.arange(n_steps, dtype=float) if time_s is None else np.asarray(time_s, float)
    keep = {n_steps - 1} if n_steps and keep_last else set()
    lower = -np.inf if after_s is None else float(after_s)
    if every_s > 0 and n_steps:
        # the first step at or after each multiple of every_s from the print's start
        origin = t[0] if origin_s is None else float(origin_s)
        first = max(np.ceil((max(t[0], lower) - origin) / every_s), 0.0)
        marks = origin + every_s * np.arange(first, np.floor((t[-1] - origin) / every_s) + 2)
        marks = marks[marks > lower]
        keep.update(np.searchsorted(t, marks).tolist())
    for when in alarm_times:
        if np.isfinite(when) and when > lower:
            keep.add(int(np.searchsorted(t, when)))
    return np.array(sorted(k for k in keep if 0 <= k < n_steps), dtype=np.int64)


def encode_all(
    arrays: dict, policy: StoragePolicy, alarm_times=(), every_s=None, *, part=None
) -> dict:
    """{name: (codec, blob)} of a print's arrays under ``policy``.

    ``every_s`` overrides the policy's key-frame spacing (≤ 0: only the last step and
    the alarms, what ``machine compact`` keeps of old prints). ``part``: the arrays are a
    part of a print, a dict with ``first_step`` (its first step's index in the print),
    ``origin_s`` (the print's start), ``after_s`` (the time of the step before it; None
    for the first part) and ``last`` (the print's last part): key frames are chosen as for
    the whole print (:func:`keyframe_steps`) and stored with their index in the print.
    """
    arrays = dict(arrays)
    if "means" in arrays and "predicted_means" in arrays:
        means = np.asarray(arrays["means"], dtype=float)
        arrays["state_corrections"] = means - np.asarray(arrays.pop("predicted_means"), float)
    if "covariances" in arrays and (every_s is not None or policy.covariance_every_s > 0):
        covs = np.asarray(arrays.pop("covariances"), dtype=float)
        every = policy.covariance_every_s if every_s is None else every_s
        where = {} if part is None else {
            "origin_s": part["origin_s"], "after_s": part["after_s"], "keep_last": part["last"]
        }  # fmt: skip
        steps = keyframe_steps(len(covs), arrays.get("time_s"), every, alarm_times, **where)
        arrays["covariance_steps"] = steps + (0 if part is None else int(part["first_step"]))
        arrays["covariance_keyframes"] = covs[steps]
    out = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        cast = np.float32 if name in policy.float32 and value.dtype.kind == "f" else None
        if cast is not None and not _fits_float32(value):
            cast = None  # a value beyond float32's range would become inf: keep float64
        out[name] = encode(value, cast)
    return out


def _fits_float32(value: np.ndarray) -> bool:
    finite = np.abs(value[np.isfinite(value)])
    return not finite.size or float(finite.max()) <= float(np.finfo(np.float32).max)


def join_parts(parts: dict) -> dict:
    """{name: array} of a print stored in parts ({name: [decoded part, ...]} in part order):
    each array's parts joined along the steps; the covariance key frames sorted by step,
    each step once (a later part may add the key frame of an alarm whose onset lay in an
    earlier part).

    >>> joined = join_parts({"time_s": [np.arange(2.0), np.arange(2.0, 4.0)],
    ...                      "covariance_steps": [np.array([3]), np.array([0, 3])],
    ...                      "covariance_keyframes": [np.ones((1, 1)), np.zeros((2, 1))]})
    >>> joined["time_s"].tolist(), joined["covariance_steps"].tolist()
    ([0.0, 1.0, 2.0, 3.0], [0, 3])
    """
    out = {name: np.concatenate(chunks, axis=0) for name, chunks in parts.items()}
    if "covariance_steps" in out and "covariance_keyframes" in out:
        steps, first = np.unique(out["covariance_steps"], return_index=True)
        out["covariance_steps"] = steps
        out["covariance_keyframes"] = out["covariance_keyframes"][first]
    return out


def expand(stored: dict) -> dict:
    """Decoded arrays as the rest of ajtwin uses them: float64, ``predicted_means``
    rebuilt from the means and the state corrections."""
    out = {
        name: (value.astype(np.float64) if value.dtype == np.float32 else value)
        for name, value in stored.items()
    }
    if "state_corrections" in out and "means" in out:
        out["predicted_means"] = out["means"] - out.pop("state_corrections")
    return out
