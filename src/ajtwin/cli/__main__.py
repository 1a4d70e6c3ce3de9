"""``python -m ajtwin.cli``: the ``ajtwin`` command."""

from ajtwin.cli import run

run()
