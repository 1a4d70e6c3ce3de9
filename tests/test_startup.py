"""Start-up: the persistent compilation cache and import hygiene of the CLI.

Each check runs in a fresh interpreter (the cache is configured at import of
``ajtwin._jax``, once per process).
"""

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _python(code: str, **env_extra) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AJTWIN_")}
    env.update(PYTHONPATH=SRC, JAX_PLATFORMS="cpu", **env_extra)
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


_CACHE_PROBE = """
import json
from ajtwin._jax import jax, jnp, compilation_cache_dir
f = jax.jit(lambda x: jnp.sin(x) * 3.0 + x**2)
f(jnp.arange(7.0)).block_until_ready()
d = compilation_cache_dir()
print(json.dumps({"dir": None if d is None else str(d),
                  "entries": 0 if d is None else len(list(d.iterdir())),
                  "x64": bool(jax.config.jax_enable_x64)}))
"""


def test_compilation_cache_is_private_versioned_and_written(tmp_path):
    base = tmp_path / "cache"
    first = json.loads(_python(_CACHE_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert first["x64"]
    directory = Path(first["dir"])
    assert directory.parent == base
    import jax

    from ajtwin import __version__

    assert directory.name == f"jax-{jax.__version__}-ajtwin-{__version__}"
    # entries are executable code: the directories are the user's alone
    for path in (base, directory):
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode & (stat.S_IRWXG | stat.S_IRWXO) == 0, oct(mode)
    # thresholds low enough that a tiny function is written
    assert first["entries"] >= 1
    second = json.loads(_python(_CACHE_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert second["entries"] == first["entries"]  # hit, nothing new written


def test_compilation_cache_switch_off(tmp_path):
    base = tmp_path / "cache"
    probe = json.loads(_python(_CACHE_PROBE, AJTWIN_CACHE_DIR=str(base), AJTWIN_NO_CACHE="1"))
    assert probe["dir"] is None
    assert not base.exists()


def test_group_writable_cache_directory_is_tightened(tmp_path):
    base = tmp_path / "cache"
    base.mkdir()
    os.chmod(base, 0o777)
    probe = json.loads(_python(_CACHE_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert probe["dir"] is not None
    assert stat.S_IMODE(base.stat().st_mode) == 0o700


_IMPORTS_PROBE = """
import json, sys
from click.testing import CliRunner
from ajtwin.cli import main
result = CliRunner().invoke(main, {args!r})
heavy = ("jax", "pandas", "scipy", "torch", "cv2", "matplotlib", "ajtwin.simulation")
print(json.dumps({{"code": result.exit_code, "output": result.output,
                  "loaded": sorted(m for m in heavy if m in sys.modules)}}))
"""


def test_help_lists_every_command_without_heavy_imports():
    from ajtwin.cli import SUBCOMMANDS

    probe = json.loads(_python(_IMPORTS_PROBE.format(args=["--help"])))
    assert probe["code"] == 0
    for name in SUBCOMMANDS:
        assert f"  {name} " in probe["output"], name
    assert probe["loaded"] == []


def test_estimate_help_does_not_load_torch_opencv_or_matplotlib():
    probe = json.loads(_python(_IMPORTS_PROBE.format(args=["estimate", "--help"])))
    assert probe["code"] == 0
    assert not {"torch", "cv2", "matplotlib"} & set(probe["loaded"])


def test_estimate_path_does_not_load_torch_opencv_or_matplotlib():
    code = (
        "import sys, json\n"
        "import ajtwin.estimation.twin, ajtwin.io.records, ajtwin.cli.estimate\n"
        "print(json.dumps(sorted(m for m in ('torch', 'cv2', 'matplotlib') if m in sys.modules)))"
    )
    assert json.loads(_python(code)) == []


_EXPORT_PROBE = """
import json, sys
import numpy as np
from ajtwin._jax import jax, jnp, compilation_cache_dir
from ajtwin._aot import exported_jit
traced, lowered = [], []
_deserialize = jax.export.deserialize
jax.export.deserialize = lambda data: lowered.append(1) or _deserialize(data)

def model(x, scale, gate=2.0, kind="square"):
    traced.append(kind)  # runs only when JAX traces the Python function
    y = x * scale if kind == "scale" else x**2
    return {"y": y, "n": jnp.sum(x > gate), "solve": jnp.linalg.solve(jnp.eye(2) * scale, x[:2])}

f = exported_jit(model, static_argnames=("kind",))
x = jnp.linspace(0.0, 3.0, 7)
out = f(x, 1.5)
ref = jax.jit(model, static_argnames=("kind",))(x, 1.5)
vm = jax.vmap(lambda v: f(v, 2.0)["y"])(jnp.ones((3, 2)))  # a tracer: plain jit
other = f(x, 1.5, kind="scale")
d = compilation_cache_dir()
files = sorted(p.name for p in (d / "exported").iterdir()) if d else []
same = bool(np.array_equal(out["y"], ref["y"])) and int(ref["n"]) == int(out["n"])
print(json.dumps({"y": np.asarray(out["y"]).tolist(), "n": int(out["n"]), "same": same,
                  "vmap": np.asarray(vm).tolist(), "scale": np.asarray(other["y"]).tolist(),
                  "solve": np.asarray(out["solve"]).tolist(),
                  "lowered": len(lowered),
                  "traced": traced, "files": files}))
"""


def test_exported_programs_skip_tracing_in_a_new_process(tmp_path):
    """ajtwin._aot: the compiled program is loaded by the next process (no tracing, no
    lowering; LAPACK's solve works in it), results equal plain jax.jit's, static arguments
    and shapes get entries of their own, transformations and a switched-off cache take the
    plain path, a broken entry is traced again."""
    base = tmp_path / "cache"
    first = json.loads(_python(_EXPORT_PROBE, AJTWIN_CACHE_DIR=str(base)))
    x = [3.0 * i / 6 for i in range(7)]
    assert first["same"]
    assert first["y"] == [v**2 for v in x] and first["n"] == 2
    assert first["scale"] == [1.5 * v for v in x]
    assert first["solve"] == [0.0, 0.5 / 1.5]
    assert first["vmap"] == [[1.0, 1.0]] * 3
    # traced: square (export), square (plain jit reference), square (vmap), scale (export)
    assert sorted(first["traced"]) == ["scale", "square", "square", "square"]
    suffixes = sorted(name.rsplit(".", 1)[1] for name in first["files"])
    # two programs, each lowered, compiled and with its output tree
    assert suffixes == ["stablehlo", "stablehlo", "tree", "tree", "xla", "xla"]

    second = json.loads(_python(_EXPORT_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert second["y"] == first["y"] and second["scale"] == first["scale"]
    assert second["solve"] == first["solve"]
    assert sorted(second["traced"]) == ["square", "square"]  # only the reference and vmap
    assert second["lowered"] == 0  # both loaded compiled: no StableHLO read back
    assert second["files"] == first["files"]

    # a truncated entry (a crash mid-write on a system without atomic rename) is retraced
    directory = next(base.iterdir()) / "exported"
    for path in [*directory.glob("*.stablehlo"), *directory.glob("*.xla")]:
        path.write_bytes(path.read_bytes()[:20])
    third = json.loads(_python(_EXPORT_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert third["y"] == first["y"] and third["scale"] == first["scale"]
    assert sorted(third["traced"]) == sorted(first["traced"])
    # retraced, the programs compiled from JAX's cache: an executable read back from it
    # serializes without its kernels, so only the lowered programs are kept ...
    assert not list(directory.glob("*.xla"))
    # ... and the next process runs from them
    fourth = json.loads(_python(_EXPORT_PROBE, AJTWIN_CACHE_DIR=str(base)))
    assert fourth["y"] == first["y"] and fourth["solve"] == first["solve"]
    assert fourth["lowered"] == 2 and sorted(fourth["traced"]) == ["square", "square"]

    off = json.loads(_python(_EXPORT_PROBE, AJTWIN_CACHE_DIR=str(base), AJTWIN_NO_CACHE="1"))
    assert off["y"] == first["y"] and off["files"] == []


_CONSTANT_PROBE = """
import json
from typing import NamedTuple
import numpy as np
from ajtwin._jax import jax, jnp
from ajtwin._aot import exported_jit
traced = []

class Params(NamedTuple):
    gain: float
    poly: tuple

class Spec(NamedTuple):
    params: Params
    scale: object

def model(spec, x):
    traced.append(spec.params is None or isinstance(spec.params.gain, jax.core.Tracer))
    c0, c1 = spec.params.poly
    return spec.scale * (spec.params.gain * x + c0 + c1 * x**2)

f = exported_jit(model, constant_fields=(("spec", "params"),))
x = jnp.linspace(0.0, 1.0, 5)
a = Spec(Params(2.0, (1.0, 0.5)), jnp.ones(5))
b = Spec(Params(3.0, (1.0, 0.5)), jnp.ones(5))
out_a, out_b = f(a, x), f(b, x)
again_a = f(a, x)
as_arrays = f(Spec(Params(jnp.asarray(3.0), (jnp.asarray(1.0), 0.5)), jnp.ones(5)), x)
grad = jax.grad(lambda g: f(Spec(Params(g, (1.0, 0.5)), jnp.ones(5)), x).sum())(2.0)
print(json.dumps({"a": np.asarray(out_a).tolist(), "b": np.asarray(out_b).tolist(),
                  "again_a": np.asarray(again_a).tolist(), "arrays": np.asarray(as_arrays).tolist(),
                  "grad": float(grad), "traced": traced}))
"""


@pytest.mark.parametrize("no_cache", ["0", "1"])
def test_constant_fields_compile_each_value_in_and_stay_differentiable(tmp_path, no_cache):
    """ajtwin._aot ``constant_fields``: concrete parameters are compiled in (one program per
    value, never a stale one), concrete jax scalars count as concrete, and under ``grad`` the
    same field is an ordinary traced argument with the right derivative."""
    run = json.loads(
        _python(_CONSTANT_PROBE, AJTWIN_CACHE_DIR=str(tmp_path / "c"), AJTWIN_NO_CACHE=no_cache)
    )
    x = [i / 4 for i in range(5)]
    assert run["a"] == pytest.approx([2.0 * v + 1.0 + 0.5 * v**2 for v in x], rel=1e-15)
    assert run["b"] == pytest.approx([3.0 * v + 1.0 + 0.5 * v**2 for v in x], rel=1e-15)
    assert run["again_a"] == run["a"] and run["arrays"] == run["b"]
    assert run["grad"] == pytest.approx(sum(x), rel=1e-15)
    # a and b each traced once with constants (False), the repeat of a and b-as-arrays not
    # at all, the gradient once with the gain traced (True)
    assert run["traced"] == [False, False, True]


_EXIT_PROBE = """
import atexit, sys, threading, time
from pathlib import Path
from ajtwin.cli import run
out = Path(sys.argv[1])
atexit.register(lambda: (out / "atexit").write_text("ran"))
class Kept:  # cleared only by the interpreter's teardown
    def __del__(self):
        (out / "teardown").write_text("ran")
kept = Kept()
def late():
    time.sleep(0.3)
    (out / "thread").write_text("done")
if sys.argv[2] == "thread":
    threading.Thread(target=late).start()  # not a daemon: the exit must wait for it
sys.argv = ["ajtwin", *sys.argv[3:]]
run()
"""


@pytest.mark.parametrize("thread", ["none", "thread"])
def test_the_command_exits_with_its_code_after_the_exit_handlers_and_threads(tmp_path, thread):
    """ajtwin.cli.run skips the interpreter's teardown, not what Python's exit does before it:
    the exit handlers run, a thread still running is waited for, the output is whole and the
    status is the command's."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AJTWIN_")}
    env.update(PYTHONPATH=SRC)

    def ajtwin(*args):
        command = [sys.executable, "-c", _EXIT_PROBE, str(tmp_path), thread, *args]
        return subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)

    helped = ajtwin("--help")
    assert helped.returncode == 0
    assert helped.stdout.rstrip().endswith("docs/explanation/glossary.md.")  # the epilog's end
    assert (tmp_path / "atexit").read_text() == "ran"
    assert (tmp_path / "thread").exists() == (thread == "thread")
    # the teardown is skipped, unless a thread made the exit Python's own
    assert (tmp_path / "teardown").exists() == (thread == "thread")

    (tmp_path / "atexit").unlink()
    wrong = ajtwin("no-such-command")
    assert wrong.returncode == 2 and "No such command 'no-such-command'" in wrong.stderr
    assert (tmp_path / "atexit").read_text() == "ran"


_EM_PROBE = """
import json, pickle
import numpy as np
import ajtwin._aot as aot
from ajtwin._jax import compilation_cache_dir
from ajtwin.estimation import Twin
loaded = []
_load_executable = aot._load_executable
aot._load_executable = lambda path: loaded.append(path.stem) or _load_executable(path)
twin = Twin.default(window_s=60, every_s=30, early_em_s=(20,))
u = np.array([375.0, 23.0, 50.0])
y = np.asarray(twin.model.outputs(np.array([3.5, 1.0, 0.0, 0.0, 4.6e-7]), u))
n = 100
noisy = y * (1 + 0.01 * np.random.default_rng(0).standard_normal((n, 5)))
run = twin.run(inputs=np.tile(u, (n, 1)), measurements=noisy, time_s=np.arange(float(n)))
folder = compilation_cache_dir() / "exported"
# em_loop's entries: the only kept program whose result holds a SmootherResult
trees = {p.stem: str(pickle.loads(p.read_bytes())) for p in folder.glob("*.tree")}
em = sorted(key for key, tree in trees.items() if "SmootherResult" in tree)
windows = (run.theta_history["time_s"] - run.theta_history["window_start_s"] + 1).tolist()
print(json.dumps({"windows": windows, "em": em,
                  "executables": [k for k in em if (folder / f"{k}.xla").exists()],
                  "loaded": [k for k in loaded if k in em]}))
"""


def test_the_early_and_full_em_windows_share_one_kept_executable(tmp_path):
    """The twin's early EM window (20 steps here) runs padded to the full window (60): one
    EM program is compiled and kept, and a new process loads that one executable only."""
    cache = str(tmp_path / "cache")
    first = json.loads(_python(_EM_PROBE, AJTWIN_CACHE_DIR=cache))
    assert first["windows"] == [20.0, 60.0, 60.0]
    assert len(first["em"]) == 1 and first["executables"] == first["em"]
    second = json.loads(_python(_EM_PROBE, AJTWIN_CACHE_DIR=cache))
    assert second["windows"] == first["windows"] and second["em"] == first["em"]
    assert second["loaded"] == first["em"]


_PREFETCH_PROBE = """
import json, threading
import numpy as np
from ajtwin import _aot

def double(x):
    return 2.0 * x

exported = _aot.exported_jit(double)
fresh = exported(np.ones(4))  # traced and kept, or loaded when kept by a process before
loaders, exports = [], []
load, export = _aot._load, _aot._export
_aot._load = lambda *a: loaders.append(threading.current_thread().name) or load(*a)
_aot._export = lambda *a: exports.append(1) or export(*a)
again = _aot.exported_jit(double)  # nothing loaded yet in this wrapper
again.prefetch(np.zeros(3))  # never kept at this shape: nothing to load
again.prefetch(np.zeros(4))
result = again(np.arange(4.0))
print(json.dumps({"loaders": loaders, "exports": len(exports), "result": result.tolist()}))
"""


def test_a_prefetched_program_is_loaded_in_the_background_and_used_by_the_call(tmp_path):
    probe = json.loads(_python(_PREFETCH_PROBE, AJTWIN_CACHE_DIR=str(tmp_path / "c")))
    assert probe["result"] == [0.0, 2.0, 4.0, 6.0]
    # one load, on the prefetch's own thread; the call took its result, traced nothing
    assert probe["loaders"] == ["ajtwin-prefetch-__main__.double"], probe
    assert probe["exports"] == 0
