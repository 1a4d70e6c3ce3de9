"""The ``ajtwin`` command line.

One module per command group (``ajtwin/cli/<group>.py``), each imported only when its
command runs, so ``ajtwin --help`` stays fast and one area's heavy imports (JAX, PyTorch,
OpenCV) never slow down another's command. A command module parses options and calls
library functions; it holds no physics and no workflow of its own.
"""

from __future__ import annotations

import atexit
import importlib
import os
import sys
import threading
from pathlib import Path

import click

from ajtwin import __version__

#: the ajtwin package folder (the commands live in its cli/ subfolder)
_PACKAGE_DIR = Path(__file__).resolve().parents[1]

# name -> "module:attribute" of a click command or group
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("ajtwin.cli.demo:demo_command", "Run the end-to-end demo on the embedded default."),
    "openloop": ("ajtwin.cli.openloop:openloop", "Open-loop run of the digital model."),
    "simulate": ("ajtwin.cli.simulate:simulate", "Virtual printer: simulate a print record."),
    "plot": ("ajtwin.cli.simulate:plot", "Plot a print record (inputs, outputs, truth)."),
    "estimate": ("ajtwin.cli.estimate:estimate", "Run the twin (EKF/RTS/EM) on a print record."),
    "experiment": ("ajtwin.cli.experiment:experiment", "Reproduce the paper's experiments."),
    "render": ("ajtwin.cli.vision:render", "Render alignment-camera video from a print."),
    "extract": ("ajtwin.cli.vision:extract", "Linewidth/overspray from alignment-camera video."),
    "cnn": ("ajtwin.cli.cnn:cnn", "Height-profile CNN: train and infer Q_m."),
    "cfd": ("ajtwin.cli.cfd:cfd", "CFD macro-model with OpenFOAM: case, run, sweep, fit."),
    "machine": (
        "ajtwin.cli.machine:machine",
        "Machine registry: add, show, history, drop, compact, backup.",
    ),
    "ingest": ("ajtwin.cli.ingest:ingest", "Ingest a print into a machine's twin."),
    "reprocess": (
        "ajtwin.cli.reprocess:reprocess",
        "Re-run the twin over stored prints (Dask): a new version of results.",
    ),
    "store": ("ajtwin.cli.store:store", "The registry as a whole: copy (SQLite ⇄ PostgreSQL)."),
    "forecast": ("ajtwin.cli.forecast:forecast", "Forecast outputs under planned input changes."),
    "advise": ("ajtwin.cli.advise:advise", "Input settings that hold a target linewidth."),
    "develop": (
        "ajtwin.cli.develop:develop",
        "Bring up a new ink: the test lines to print, then the recipe.",
    ),
    "control": (
        "ajtwin.cli.control:control",
        "Closed-loop MPC of linewidth: a live machine over OPC UA, or simulate.",
    ),
    "printer": ("ajtwin.cli.printer:printer", "The virtual printer as a live OPC UA machine."),
    "live": ("ajtwin.cli.live:live", "The live twin beside a machine (OPC UA or a growing CSV)."),
    "dashboard": ("ajtwin.cli.dashboard:dashboard", "Browser dashboard: fleet, machines, what-if."),
    "job": ("ajtwin.cli.job:job", "The machine's program: summary, timeline, part plot."),
    "camera": ("ajtwin.cli.camera:camera", "The alignment camera's geometry: calibrate."),
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        """The commands whose module is installed, sorted."""
        return sorted(name for name in SUBCOMMANDS if self._available(name))

    @staticmethod
    def _available(name: str) -> bool:
        # A file check, not importlib.util.find_spec: find_spec imports the parent
        # packages (ajtwin.simulation pulls in JAX, pandas, scipy.signal: ~1.5 s).
        parts = SUBCOMMANDS[name][0].split(":")[0].split(".")[1:]
        base = _PACKAGE_DIR.joinpath(*parts)
        return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()

    def get_command(self, ctx, name):
        """The command ``name``, its module imported now (None: unknown)."""
        if name not in SUBCOMMANDS or not self._available(name):
            return None
        target, _ = SUBCOMMANDS[name]
        module_name, attr = target.split(":")
        module = importlib.import_module(module_name)
        return getattr(module, attr, None)

    def invoke(self, ctx):
        """Run the command; an error that is a sentence for the user (``shown_as_sentence``:
        a failure of the registry's file or disk — full, read-only, damaged —
        :class:`ajtwin.store.connection.StoreError`) ends it with that sentence, never a
        traceback, whichever command met it. (Recognised by the attribute: this module
        imports no part of ajtwin but its version, to keep ``--help`` fast.)"""
        try:
            return super().invoke(ctx)
        except Exception as exc:
            if getattr(exc, "shown_as_sentence", False):
                raise click.ClickException(str(exc)) from None
            raise

    def format_commands(self, ctx, formatter):
        """The command list of ``--help`` from :data:`SUBCOMMANDS` (no module imported)."""
        rows = [(name, SUBCOMMANDS[name][1]) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


#: where ``ajtwin --help`` sends the reader (the site ``make docs`` builds from docs/)
DOCS_EPILOG = (
    "Documentation: `make docs` in the source folder builds the site into site/ (open "
    "site/index.html; `make docs-serve` serves it with search). Its pages: docs/, starting "
    "with docs/tutorial.md; the Python API: site/reference/api/ajtwin.html. The words and "
    "symbols the commands use (θ, NIS, EM, CUSUM, ΔR_N, …): docs/explanation/glossary.md."
)


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog=DOCS_EPILOG,
)
@click.version_option(__version__, prog_name="ajtwin")
def main():
    """ajtwin — a digital twin of Aerosol Jet printers.

    Reads the machine's logs and alignment-camera video, infers the hidden
    states that make lines drift (droplet size, aerosol density, ink level,
    ink building up in tube and nozzle), warns early, and forecasts what an
    input change will do. Units: µm, mL, mA, sccm, Pa, φ_A in ppm, Q_m in nL/s
    (docs/reference/model.md §3); times in minutes past the print's start.
    """


def run() -> None:
    """The ``ajtwin`` command: :func:`main`, then an exit without the interpreter's teardown.

    Once a command that loaded JAX is done, CPython spends another 0.2–0.35 s tearing the
    process down (clearing every module, freeing XLA's executables) with nothing left to
    say. So when :func:`main` has returned or exited, the output is flushed, the exit
    handlers run (logging's flush, temporary files' clean-up, worker pools), and the
    process ends with the command's exit code. While a thread that is not a daemon still
    runs (something the command started and did not stop), Python's own exit is taken,
    which waits for it. Library users and tests call :func:`main`, which never does this.
    """
    try:
        main(standalone_mode=True)  # ends in SystemExit carrying the command's code
    except SystemExit as exc:
        code = exc.code
    else:
        code = 0
    status = exit_status(code)
    if any(
        t.is_alive() and not t.daemon
        for t in threading.enumerate()
        if t is not threading.main_thread()
    ):
        sys.exit(code)
    if isinstance(code, str):
        print(code, file=sys.stderr)  # what sys.exit("message") prints
    atexit._run_exitfuncs()  # the handlers Python's exit would run, in its order
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass  # a closed pipe or stream: nothing more can reach the reader
    os._exit(status)


def exit_status(code) -> int:
    """The process status ``sys.exit(code)`` gives: None → 0, an int as it is, else 1.

    >>> exit_status(None), exit_status(2), exit_status("refused")
    (0, 2, 1)
    """
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    return 1
