"""ajtwin.simulation — the virtual AJ printer and its scenarios (docs/reference/scenarios.md).

:func:`simulate` turns a scenario and a seed into a :class:`ajtwin.io.PrintRecord`
with known truth; :func:`run_virtual_print` keeps everything behind it.
:func:`simulate_job` prints a machine program (model reference §12).
"""

from ajtwin.simulation.job_print import CameraSettings, JobSettings, run_job_print, simulate_job
from ajtwin.simulation.printer import VirtualPrint, run_virtual_print, simulate
from ajtwin.simulation.scenarios import Scenario, list_scenarios, load_scenario

__all__ = [
    "simulate",
    "run_virtual_print",
    "simulate_job",
    "run_job_print",
    "CameraSettings",
    "JobSettings",
    "VirtualPrint",
    "Scenario",
    "load_scenario",
    "list_scenarios",
]
