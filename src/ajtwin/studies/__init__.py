"""Studies: evaluation that is not the product — the paper's experiments, the detector and
control studies, soaks, the accuracy studies of the twin on held-out virtual machines.

Nothing in the library imports this package (the commands that run a study do). Each
study runs as ``python -m ajtwin.studies.<name>`` or through its command.
"""

import os
import platform


def machine_description() -> str:
    """The computer a study ran on, for its report: platform and CPU cores."""
    cpu = platform.processor() or platform.machine()
    return f"{platform.platform()}, {cpu}, {os.cpu_count()} cores"
