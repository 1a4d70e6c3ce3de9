"""The ``ajtwin`` command lines a page of the documentation shows, to run them as written."""

from __future__ import annotations

import re
import shlex

BASH_BLOCK = re.compile(r"^```bash\n(.*?)^```", re.S | re.M)


def ajtwin_commands(markdown: str) -> list[list[str]]:
    """The ``ajtwin …`` lines of the ``bash`` blocks of ``markdown``, in order, as argument
    lists without ``ajtwin`` (comments dropped).

    >>> ajtwin_commands("```bash\\najtwin machine add lab1   # one twin\\nls\\n```\\n")
    [['machine', 'add', 'lab1']]
    """
    commands = []
    for block in BASH_BLOCK.findall(markdown):
        for line in block.splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "ajtwin":
                commands.append(words[1:])
    return commands
