"""``jax.jit`` whose traced program is kept on disk: a new process skips tracing.

JAX's persistent compilation cache (:mod:`ajtwin._jax`) skips XLA's compilation, but
every new process still *traces* a jitted function in Python and lowers it to
StableHLO to find its cache key — for the EM loop and the filter of ``ajtwin
estimate`` about 0.8 s of a 3.3 s run. :func:`exported_jit` keeps, beside JAX's own
cache, the lowered program (``jax.export``, serialized) and the executable XLA compiled
from it, so a later process loads the executable and neither traces nor lowers. An
executable is kept only when every external routine it calls is LAPACK's (filled in
before loading); a program calling any other (whose address need not hold in another
process) keeps its lowered form alone, compiled from JAX's cache by the next process.

The stored program is found by a key of: the function's module and name, the JAX
and jaxlib versions, the machine's architecture, ``XLA_FLAGS``, a hash of ajtwin's own
source and data files (any edit makes new entries), the pytree structure, shapes,
dtypes and weak types of the arguments, and the static
arguments (only values with a stable description: module-level functions, named
tuples and frozen dataclasses of them, numbers, strings; anything else is plain
``jax.jit``). Calls under a JAX transformation (a tracer among the arguments: the
function called inside another jit, a vmap, a grad) and processes without the cache
(``AJTWIN_NO_CACHE=1``) take the plain ``jax.jit`` path, so the results are the same
function's either way (tested: ``tests/test_startup.py``).

Examples
--------
>>> from ajtwin._aot import exported_jit
>>> from ajtwin._jax import jnp
>>> double = exported_jit(lambda x: 2 * x)
>>> float(double(jnp.ones(())))
2.0
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import hashlib
import inspect
import os
import pickle
import platform
import re
import threading
import types
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from ajtwin._jax import (
    compilation_cache_dir,
    jax,
    jaxlib_version,
    lapack_targets,
    serialize_executable,
)

_PACKAGE = Path(__file__).resolve().parent
_SOURCE_SUFFIXES = (".py", ".toml", ".csv")


@functools.cache
def source_digest() -> str:
    """SHA-256 over ajtwin's source and data files (names and bytes), computed once."""
    h = hashlib.sha256()
    for path in sorted(_PACKAGE.rglob("*")):
        if path.suffix in _SOURCE_SUFFIXES and "__pycache__" not in path.parts:
            h.update(str(path.relative_to(_PACKAGE)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def _stable(value):
    """A description of a static argument that is the same in every process, or None."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return repr(value)
    if isinstance(value, types.FunctionType) and "<" not in value.__qualname__:
        return f"{value.__module__}.{value.__qualname__}"
    if isinstance(value, tuple):
        parts = [_stable(v) for v in value]
        if any(p is None for p in parts):
            return None
        return f"{type(value).__module__}.{type(value).__qualname__}({','.join(parts)})"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        if not value.__dataclass_params__.frozen:
            return None
        parts = [_stable(getattr(value, f.name)) for f in dataclasses.fields(value)]
        if any(p is None for p in parts):
            return None
        return f"{type(value).__module__}.{type(value).__qualname__}({','.join(parts)})"
    if isinstance(value, np.ndarray):
        return f"ndarray({value.dtype},{value.shape},{hashlib.sha256(value.tobytes()).hexdigest()})"
    return None


def _concrete_constant(value):
    """``value`` with every leaf a Python float, or None if any leaf is not concrete.

    The result is hashable (NamedTuples and tuples of floats), so it can be a static
    argument of ``jax.jit`` and be described by :func:`_stable`.
    """
    leaves, tree = jax.tree_util.tree_flatten(value)
    if not leaves:
        return None
    floats = []
    for leaf in leaves:
        if isinstance(leaf, jax.core.Tracer):
            return None
        array = np.asarray(leaf)
        if array.shape != () or not np.issubdtype(array.dtype, np.number):
            return None
        floats.append(float(array))
    return jax.tree_util.tree_unflatten(tree, floats)


def exported_jit(
    fun,
    *,
    static_argnames: tuple[str, ...] = (),
    constant_fields: tuple[tuple[str, str], ...] = (),
):
    """``jax.jit(fun, static_argnames=...)``, with its lowered program kept on disk.

    Same call signature and results as the jitted function. Positional and keyword
    arguments are bound to ``fun``'s signature (defaults filled in), so a call written
    either way finds the same entry.

    ``constant_fields`` names ``(argument, field)`` pairs of NamedTuple arguments (e.g.
    ``("spec", "params")``: the physical parameters inside the filter's model spec)
    that are compiled in as constants whenever all their leaves are concrete scalars.
    XLA then folds what depends on them alone (the droplet quadrature's nodes, the
    slip correction's 1/λ, …) instead of recomputing it at every step of a scan: a
    third of an EKF step (docs/explanation/performance.md, Round 5). Each distinct value compiles
    a program of its own (the parameters are the packaged ones in every twin, so in
    practice one); a field holding tracers (under ``grad``/``vmap`` of the caller) is
    passed as an ordinary argument — the same function either way.
    """
    constant_names = {pair: f"_constant_{pair[0]}_{pair[1]}" for pair in constant_fields}

    def with_constants(**kwargs):
        for (argument, field), hidden in constant_names.items():
            value = kwargs.pop(hidden)
            if value is not None:
                kwargs[argument] = kwargs[argument]._replace(**{field: value})
        return fun(**kwargs)

    all_static = tuple(static_argnames) + tuple(constant_names.values())
    jitted_constants = jax.jit(with_constants, static_argnames=all_static)
    signature = inspect.signature(fun)
    name = f"{fun.__module__}.{fun.__qualname__}"
    loaded: dict[str, tuple] = {}

    def _entry(args, kwargs):
        """(key, directory, arrays, in_tree, static) of a call, or None: plain ``jax.jit``
        (no cache, a tracer among the arguments, a static value without a stable key)."""
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        arguments = dict(bound.arguments)
        for (argument, field), hidden in constant_names.items():
            holder = arguments[argument]
            constant = _concrete_constant(getattr(holder, field))
            arguments[hidden] = constant
            if constant is not None:
                arguments[argument] = holder._replace(**{field: None})
        static = {k: arguments.pop(k) for k in all_static}
        dynamic = arguments
        directory = compilation_cache_dir()
        if directory is None:
            return None, (dynamic, static)
        leaves, in_tree = jax.tree_util.tree_flatten(dynamic)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
            return None, (dynamic, static)
        static_key = {k: _stable(v) for k, v in static.items()}
        if any(v is None for v in static_key.values()):
            return None, (dynamic, static)
        arrays = [np.asarray(leaf) if not isinstance(leaf, jax.Array) else leaf for leaf in leaves]
        key_text = repr(
            (
                name,
                _toolchain(),
                os.environ.get("XLA_FLAGS", ""),
                source_digest(),
                str(in_tree),
                [(a.shape, str(a.dtype), getattr(a, "weak_type", False)) for a in arrays],
                sorted(static_key.items()),
            )
        )
        key = hashlib.sha256(key_text.encode()).hexdigest()[:40]
        return (key, directory, arrays, in_tree, static), (dynamic, static)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        entry_of, (dynamic, static) = _entry(args, kwargs)
        if entry_of is None:
            return jitted_constants(**dynamic, **static)
        key, directory, arrays, in_tree, static = entry_of
        entry = loaded.get(key)
        if isinstance(entry, Future):
            entry = entry.result()  # a prefetch loading it (None: nothing kept)
        if entry is None:
            entry = _load(directory, key)
        if entry is None:
            entry = _export(directory, key, jitted_constants, in_tree, static, arrays)
        loaded[key] = entry
        run, out_tree = entry
        return jax.tree_util.tree_unflatten(out_tree, run(*arrays))

    def prefetch(*args, **kwargs) -> None:
        """Start loading the kept executable a call with arguments shaped like these would
        run, in a background thread, and return at once: XLA links an executable's machine
        code (~0.08 s per MB) without holding the GIL, so the load overlaps what the
        process does until the call. Nothing kept yet (or no cache): nothing happens, and
        the call traces and keeps as usual."""
        entry_of, _ = _entry(args, kwargs)
        if entry_of is None:
            return
        key, directory = entry_of[0], entry_of[1]
        if key in loaded or not _paths(directory, key)[2].exists():
            return
        _lapack_ready()  # here, not in two threads at once
        future: Future = Future()
        loaded[key] = future

        def load():
            try:
                future.set_result(_load(directory, key))
            except BaseException as exc:  # noqa: BLE001 — the call then loads it itself
                future.set_result(None)
                if not isinstance(exc, Exception):
                    raise

        threading.Thread(target=load, name=f"ajtwin-prefetch-{name}", daemon=True).start()

    call.prefetch = prefetch
    return call


@functools.cache
def _toolchain() -> str:
    """What an executable was built by and for: JAX, jaxlib, the CPU architecture."""
    return f"jax {jax.__version__}, jaxlib {jaxlib_version}, {platform.machine()}"


#: external routines a kept executable may call: LAPACK's, filled in by _lapack_ready
_LOADABLE_TARGET = re.compile(r"lapack_\w+")


def _paths(directory: Path, key: str) -> tuple[Path, Path, Path]:
    folder = directory / "exported"
    return folder / f"{key}.stablehlo", folder / f"{key}.tree", folder / f"{key}.xla"


def _load(directory: Path, key: str):
    program, tree, executable = _paths(directory, key)
    try:
        # the cache directory is private to this user (ajtwin._jax); the tree is a
        # pickled PyTreeDef of ajtwin's own result types
        out_tree = pickle.loads(tree.read_bytes())
        compiled = _load_executable(executable)
        if compiled is not None:
            return compiled, out_tree
        exported = jax.export.deserialize(bytearray(program.read_bytes()))
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001 — any broken entry (flatbuffers, pickle, struct) is retraced
        return None
    return jax.jit(exported.call), out_tree


def _load_executable(path: Path):
    """The compiled program kept at ``path``, or None (absent or unreadable)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    _lapack_ready()
    payload, in_tree, out_tree = pickle.loads(data)
    return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)


@functools.cache
def _lapack_ready() -> None:
    """Fill in jaxlib's LAPACK entry points, as lowering a linear solve would.

    A kept executable calls LAPACK (LU factorisation, triangular solves) through targets
    that jaxlib fills in only when the first such operation is lowered; a process that
    loads programs without lowering anything must fill them in first or the call jumps
    to nothing.
    """
    lapack_targets.initialize()


#: JAX's persistent-cache hits, per thread (counted by the listener below)
_cache_hits: collections.Counter = collections.Counter()


def _count_cache_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _cache_hits[threading.get_ident()] += 1


jax.monitoring.register_event_listener(_count_cache_hit)


def _compile(exported, shapes, key: str):
    """``exported`` compiled for ``shapes``, and whether XLA compiled it here.

    Only a program compiled in this process is kept as an executable: one read back
    from JAX's cache serializes without its kernels ("Function … not found" when the
    next process runs it). The program is named after ``key``, so JAX's cache holds it
    under a key of its own, found again only if this entry is exported again.
    """

    def run(*leaves):
        return exported.call(*leaves)

    run.__name__ = run.__qualname__ = f"ajtwin_{key}"
    thread = threading.get_ident()
    before = _cache_hits[thread]
    compiled = jax.jit(run).lower(*shapes).compile()
    return compiled, _cache_hits[thread] == before


def _export(directory: Path, key: str, jitted, in_tree, static: dict, arrays: list):
    out_trees = []

    def flat(*leaves):
        result = jitted(**jax.tree_util.tree_unflatten(in_tree, leaves), **static)
        out_leaves, out_tree = jax.tree_util.tree_flatten(result)
        out_trees.append(out_tree)  # traced once, by the export below
        return out_leaves

    shapes = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in arrays]
    exported = jax.export.export(jax.jit(flat))(*shapes)
    compiled, fresh = _compile(exported, shapes, key)
    program, tree, executable = _paths(directory, key)
    entries = [(tree, pickle.dumps(out_trees[0])), (program, exported.serialize())]
    targets = re.findall(r'call_target_name = "([^"]*)"', exported.mlir_module())
    targets += re.findall(r"custom_call @([\w.]+)", exported.mlir_module())
    keep_executable = fresh and all(_LOADABLE_TARGET.fullmatch(t) for t in targets)
    if keep_executable:
        entries.append((executable, pickle.dumps(serialize_executable.serialize(compiled))))
    try:
        program.parent.mkdir(mode=0o700, exist_ok=True)
        # write then rename: a killed process never leaves a half entry under the key
        for path, data in entries:
            partial = path.with_suffix(path.suffix + f".{os.getpid()}.part")
            partial.write_bytes(data)
            os.replace(partial, path)
        if not keep_executable:
            executable.unlink(missing_ok=True)  # a broken one sent this process here
    except OSError:
        pass  # read-only cache: this process still runs from what it traced
    return compiled, out_trees[0]
