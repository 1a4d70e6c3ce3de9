"""The ``ajtwin`` command line.

Subcommands live next to the code they drive (``ajtwin/<area>/cli.py``) and are
imported lazily, so ``ajtwin --help`` stays fast and one area's heavy imports
(JAX, PyTorch, OpenCV) never slow down another's command.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import click

from ajtwin import __version__

_PACKAGE_DIR = Path(__file__).resolve().parent

# name -> "module:attribute" of a click command or group
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("ajtwin.demo:demo_command", "Run the end-to-end demo on the embedded default."),
    "openloop": ("ajtwin.simulation.openloop:openloop", "Open-loop run of the digital model."),
    "simulate": ("ajtwin.simulation.cli:simulate", "Virtual printer: simulate a print record."),
    "plot": ("ajtwin.simulation.cli:plot", "Plot a print record (inputs, outputs, truth)."),
    "estimate": ("ajtwin.estimation.cli:estimate", "Run the twin (EKF/RTS/EM) on a print record."),
    "experiment": ("ajtwin.estimation.cli:experiment", "Reproduce the paper's experiments."),
    "render": ("ajtwin.vision.cli:render", "Render alignment-camera video from a print."),
    "extract": ("ajtwin.vision.cli:extract", "Linewidth/overspray from alignment-camera video."),
    "cnn": ("ajtwin.profile_cnn.cli:cnn", "Height-profile CNN: train and infer Q_m."),
    "cfd": ("ajtwin.cfd.cli:cfd", "CFD macro-model with OpenFOAM: case, run, sweep, fit."),
    "machine": (
        "ajtwin.store.cli:machine",
        "Machine registry: add, show, history, drop, compact, backup.",
    ),
    "ingest": ("ajtwin.store.cli:ingest", "Ingest a print into a machine's twin."),
    "forecast": ("ajtwin.apps.cli:forecast", "Forecast outputs under planned input changes."),
    "advise": ("ajtwin.apps.cli:advise", "Input settings that hold a target linewidth."),
    "control": (
        "ajtwin.apps.control_cli:control",
        "Closed-loop MPC of linewidth: a live machine over OPC UA, or simulate.",
    ),
    "printer": ("ajtwin.live.cli:printer", "The virtual printer as a live OPC UA machine."),
    "live": ("ajtwin.live.cli:live", "The live twin beside a machine (OPC UA or a growing CSV)."),
    "dashboard": ("ajtwin.web.cli:dashboard", "Browser dashboard: fleet, machines, what-if."),
    "job": ("ajtwin.job.cli:job", "The machine's program: summary, timeline, part plot."),
    "camera": ("ajtwin.vision.part_cli:camera", "The alignment camera's geometry: calibrate."),
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        return sorted(name for name in SUBCOMMANDS if self._available(name))

    @staticmethod
    def _available(name: str) -> bool:
        # A file check, not importlib.util.find_spec: find_spec imports the parent
        # packages (ajtwin.simulation pulls in JAX, pandas, scipy.signal: ~1.5 s).
        parts = SUBCOMMANDS[name][0].split(":")[0].split(".")[1:]
        base = _PACKAGE_DIR.joinpath(*parts)
        return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()

    def get_command(self, ctx, name):
        if name not in SUBCOMMANDS or not self._available(name):
            return None
        target, _ = SUBCOMMANDS[name]
        module_name, attr = target.split(":")
        module = importlib.import_module(module_name)
        return getattr(module, attr, None)

    def format_commands(self, ctx, formatter):
        rows = [(name, SUBCOMMANDS[name][1]) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ajtwin")
def main():
    """ajtwin — a digital twin of Aerosol Jet printers.

    Reads the machine's logs and alignment-camera video, infers the hidden
    states that make lines drift (droplet size, aerosol density, ink level,
    ink building up in tube and nozzle), warns early, and forecasts what an
    input change will do. Units: µm, mL, mA, sccm, Pa (SPEC §3).
    """


if __name__ == "__main__":
    main()
