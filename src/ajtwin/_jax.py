"""JAX set-up shared by every JAX-using module: 64-bit floats on the CPU, and a
persistent compilation cache.

Import this module (``from ajtwin._jax import jax, jnp``) instead of ``jax``
directly so that x64 and the cache are set before any array is created.

Compilation cache
-----------------
Every new process would otherwise compile the same filter, smoother and EM
functions again (most of the wall time of ``ajtwin estimate``). The compiled
executables are kept in the user's cache directory, one sub-directory per
ajtwin and JAX version (an upgrade never reads stale entries), created with
mode 0700 (not world-writable: a cache entry is executable code).

* ``AJTWIN_NO_CACHE=1`` switches the cache off.
* ``AJTWIN_CACHE_DIR`` replaces the base directory (default
  ``$XDG_CACHE_HOME/ajtwin`` or ``~/.cache/ajtwin``; ``~/Library/Caches/ajtwin``
  on macOS, ``%LOCALAPPDATA%\\ajtwin`` on Windows).

Every compiled function is written (minimum compile time 0 s, minimum size
0 bytes): the many small functions of an EM run add up to seconds otherwise.

XLA flags (set in ``XLA_FLAGS`` before JAX is imported)
------------------------------------------------------
* ``xla_cpu_small_while_loop_byte_threshold`` (an ``xla_backend_extra_options``
  entry) = 1,000,000 bytes, XLA's default being 1 kB: XLA:CPU runs a while loop
  (every ``lax.scan``) as one dispatched operation per fused op per iteration
  unless the loop's buffers are below this size, in which case the whole loop is
  compiled into one kernel. The filter's scan over a 90-min print (~0.5 MB of
  per-step outputs) then costs 2.4 instead of 13 µs a step. ``AJTWIN_XLA_SMALL_LOOP_BYTES``
  replaces the value (``0``: XLA's own default).
* ``--xla_cpu_max_isa=AVX`` on x86-64: no FMA instructions. Inside one loop kernel
  LLVM would otherwise contract a·b + c into an FMA wherever the CPU has one, so the
  same print would give different last bits on different machines (and against the
  committed results); AVX's 256-bit vectors are kept.

A flag the user already has in ``XLA_FLAGS`` is left as it is (theirs wins). Set only
with jaxlib ≥ 0.7.1 (:data:`FLAGS_SINCE_JAXLIB`): older XLA does not know them and would
stop the process on start.

Examples
--------
>>> from ajtwin._jax import compilation_cache_dir
>>> compilation_cache_dir() is None or compilation_cache_dir().name.startswith("jax-")
True
"""

import os
import stat
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

#: bytes below which XLA:CPU compiles a whole while loop into one kernel (XLA: 1 kB)
SMALL_LOOP_BYTES = 1_000_000


#: the first jaxlib known to have both flags (older XLA would pass the unknown extra option
#: to LLVM or refuse the unknown flag, and stop the process)
FLAGS_SINCE_JAXLIB = (0, 7, 1)


def _jaxlib_version() -> tuple[int, ...]:

    try:
        text = version("jaxlib")
    except PackageNotFoundError:
        return (0,)
    parts = []
    for part in text.split(".")[:3]:
        digits = "".join(c for c in part if c.isdigit()) or "0"
        parts.append(int(digits))
    return tuple(parts)


def xla_flags(existing: str, small_loop_bytes: str | None, machine: str) -> str:
    """``XLA_FLAGS`` with ajtwin's flags added before the user's ``existing`` ones.

    A flag (or extra option) the user already sets is not added, so theirs wins.
    ``small_loop_bytes``: the ``AJTWIN_XLA_SMALL_LOOP_BYTES`` value (None or "":
    :data:`SMALL_LOOP_BYTES`; "0": leave XLA's default). ``machine``:
    ``platform.machine()``.

    >>> xla_flags("", None, "x86_64").split()  # doctest: +NORMALIZE_WHITESPACE
    ['--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000',
     '--xla_cpu_max_isa=AVX']
    >>> xla_flags("--xla_cpu_max_isa=AVX2", "0", "x86_64")
    '--xla_cpu_max_isa=AVX2'
    """
    ours = []
    value = (small_loop_bytes or "").strip() or str(SMALL_LOOP_BYTES)
    if int(value) < 0:
        raise ValueError(f"AJTWIN_XLA_SMALL_LOOP_BYTES={value}: a size in bytes, ≥ 0")
    if int(value) > 0 and "xla_cpu_small_while_loop_byte_threshold" not in existing:
        ours.append(f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={value}")
    if machine.lower() in ("x86_64", "amd64") and "--xla_cpu_max_isa" not in existing:
        ours.append("--xla_cpu_max_isa=AVX")
    return " ".join(ours + ([existing.strip()] if existing.strip() else []))


# XLA reads XLA_FLAGS once, when its backend starts
if "jax" not in sys.modules and _jaxlib_version() >= FLAGS_SINCE_JAXLIB:
    import platform

    os.environ["XLA_FLAGS"] = xla_flags(
        os.environ.get("XLA_FLAGS", ""),
        os.environ.get("AJTWIN_XLA_SMALL_LOOP_BYTES"),
        platform.machine(),
    )


import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jax.experimental import serialize_executable  # noqa: E402, F401 — for ajtwin._aot
from jaxlib.cpu import _lapack as lapack_targets  # noqa: E402, F401 — for ajtwin._aot
from jaxlib.version import __version__ as jaxlib_version  # noqa: E402, F401 — for ajtwin._aot

from ajtwin import __version__  # noqa: E402

jax.config.update("jax_enable_x64", True)

_CACHE_DIR: Path | None = None


def _user_cache_base() -> Path:
    override = os.environ.get("AJTWIN_CACHE_DIR")
    if override:
        return Path(override).expanduser()
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "ajtwin"
    if sys.platform.startswith("win"):
        local = os.environ.get("LOCALAPPDATA")
        return (Path(local) if local else Path.home() / "AppData" / "Local") / "ajtwin"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "ajtwin"


def _private_directory(path: Path) -> bool:
    """Create ``path`` (and parents) with mode 0700; False if it is not ours or is shared."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = path.stat()
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        return False
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        os.chmod(path, 0o700)  # tighten a directory we own that someone made writable
    return True


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent compilation cache at the user's cache directory.

    Returns the directory in use, or None when switched off (``AJTWIN_NO_CACHE``)
    or when the directory cannot be created or is not owned by this user.
    """
    global _CACHE_DIR
    if os.environ.get("AJTWIN_NO_CACHE", "").strip() not in ("", "0"):
        return None
    directory = _user_cache_base() / f"jax-{jax.__version__}-ajtwin-{__version__}"
    try:
        if not (_private_directory(directory.parent) and _private_directory(directory)):
            return None
    except OSError:
        return None  # read-only home etc.: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(directory))
    # write every entry: EM runs compile many small functions, each far below 1 s
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _CACHE_DIR = directory
    return directory


def compilation_cache_dir() -> Path | None:
    """The persistent compilation cache directory in use (None: off)."""
    return _CACHE_DIR


enable_compilation_cache()

__all__ = [
    "jax",
    "jnp",
    "compilation_cache_dir",
    "enable_compilation_cache",
    "xla_flags",
    "SMALL_LOOP_BYTES",
]
