"""Running OpenFOAM v1912 (Debian ``openfoam``) and reading its ASCII results.

The Debian tools need ``source /usr/share/openfoam/etc/bashrc`` first; this
module sources it once, caches the environment and runs ``blockMesh``,
``checkMesh``, ``simpleFoam`` and ``postProcess`` with it. A user without
OpenFOAM gets :class:`OpenFoamMissing` saying what to install.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

#: Where Debian's openfoam package puts its environment script.
DEFAULT_BASHRC = Path("/usr/share/openfoam/etc/bashrc")

INSTALL_HINT = (
    "OpenFOAM v1912 is needed for `ajtwin cfd`. On Debian/Ubuntu run `make openfoam` in the "
    "ajtwin checkout (it does `apt-get install -y openfoam`, as root), or set "
    "AJTWIN_OPENFOAM_BASHRC to the etc/bashrc of another OpenFOAM installation."
)


class OpenFoamMissing(RuntimeError):
    """OpenFOAM is not installed (or its bashrc cannot be sourced)."""


class OpenFoamError(RuntimeError):
    """An OpenFOAM tool failed; the message names the case, tool and log."""


def bashrc_path() -> Path:
    """OpenFOAM's environment script (``$AJTWIN_OPENFOAM_BASHRC`` or Debian's)."""
    return Path(os.environ.get("AJTWIN_OPENFOAM_BASHRC", str(DEFAULT_BASHRC)))


@functools.lru_cache(maxsize=1)
def foam_environment() -> dict[str, str]:
    """Environment after sourcing OpenFOAM's bashrc (cached).

    Raises
    ------
    OpenFoamMissing
        When the bashrc is absent or the tools are not on the sourced PATH.
    """
    rc = bashrc_path()
    if not rc.is_file():
        raise OpenFoamMissing(f"{rc} not found. {INSTALL_HINT}")
    # the bashrc reads unset variables, so no `set -u`; print the environment NUL-separated
    result = subprocess.run(
        ["bash", "-c", f'source "{rc}" >/dev/null 2>&1; env -0'],
        capture_output=True,
        check=False,
    )
    if result.returncode != 0:
        raise OpenFoamMissing(f"sourcing {rc} failed. {INSTALL_HINT}")
    env = {}
    for item in result.stdout.split(b"\0"):
        if b"=" in item:
            key, _, value = item.partition(b"=")
            env[key.decode()] = value.decode(errors="replace")
    if shutil.which("simpleFoam", path=env.get("PATH")) is None:
        raise OpenFoamMissing(f"simpleFoam not on PATH after sourcing {rc}. {INSTALL_HINT}")
    return env


def openfoam_version() -> str:
    """E.g. ``"v1912"`` (from WM_PROJECT_VERSION of the sourced environment)."""
    env = foam_environment()
    return "v" + env.get("WM_PROJECT_VERSION", "unknown").lstrip("v")


def run_tool(args: list[str], case_dir: str | Path, log_name: str, timeout: float = 3600):
    """Run one OpenFOAM utility in ``case_dir``; the log goes to ``log.<log_name>``.

    Returns the wall time [s]. Raises :class:`OpenFoamError` on a non-zero exit.
    """
    case_dir = Path(case_dir)
    log = case_dir / f"log.{log_name}"
    start = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.run(
            args,
            cwd=case_dir,
            env=foam_environment(),
            stdout=out,
            stderr=subprocess.STDOUT,
            timeout=timeout,
            check=False,
        )
    if proc.returncode != 0:
        tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-15:])
        raise OpenFoamError(
            f"{args[0]} failed in {case_dir} (exit {proc.returncode}); see {log}:\n{tail}"
        )
    return time.perf_counter() - start


def latest_time(case_dir: str | Path) -> str:
    """Name of the latest numeric time directory other than 0."""
    times = []
    for child in Path(case_dir).iterdir():
        try:
            value = float(child.name)
        except ValueError:
            continue
        if child.is_dir() and value > 0:
            times.append((value, child.name))
    if not times:
        raise OpenFoamError(f"{case_dir}: no solution time directory written")
    return max(times)[1]


_LIST_START = re.compile(
    r"internalField\s+nonuniform\s+List<(scalar|vector)>\s*\n?\s*(\d+)\s*\n?\s*\("
)


def read_internal_field(path: str | Path) -> np.ndarray:
    """Internal field of an ASCII OpenFOAM volField file: (n,) scalars or (n, 3) vectors.

    Raises
    ------
    OpenFoamError
        If the file is not an ASCII nonuniform field or its length does not match.
    """
    text = Path(path).read_text()
    match = _LIST_START.search(text)
    if match is None:
        raise OpenFoamError(f"{path}: no ASCII 'internalField nonuniform List<...>' found")
    kind, count = match.group(1), int(match.group(2))
    body_start = match.end()
    body_end = text.index("\n)", body_start)
    body = text[body_start:body_end].replace("(", " ").replace(")", " ")
    values = np.array(body.split(), dtype=float)
    width = 3 if kind == "vector" else 1
    if values.size != count * width:
        raise OpenFoamError(f"{path}: expected {count} {kind}s, parsed {values.size / width:g}")
    return values.reshape(count, 3) if width == 3 else values


_RESIDUAL = re.compile(r"Solving for (Ux|Uy|p), Initial residual = ([0-9.eE+-]+)")
_CONVERGED = re.compile(r"SIMPLE solution converged in (\d+) iterations")
_TIME = re.compile(r"^Time = (\d+)", re.MULTILINE)


def parse_solver_log(path: str | Path) -> dict:
    """Convergence facts from a simpleFoam log: iterations, converged, final residuals."""
    text = Path(path).read_text(errors="replace")
    times = _TIME.findall(text)
    final = {}
    for name, value in _RESIDUAL.findall(text):
        final[name] = float(value)
    converged = _CONVERGED.search(text)
    return {
        "iterations": int(times[-1]) if times else 0,
        "converged": converged is not None,
        "final_residuals": final,
    }
