"""Errors and warnings of the job reader: each names the file, the line and its text."""

from __future__ import annotations

__all__ = ["ProgramError", "ProgramWarning"]


# characters of the offending line shown in a message (a 30 000-character line is cut)
_SHOWN = 200


class ProgramError(ValueError):
    """A program the reader refuses: unknown command, unreadable number, bad geometry.

    Attributes
    ----------
    path : str
        The program file (``"<text>"`` for a program given as a string).
    line : int or None
        1-based line number of the offending statement (None: the program as a whole).
    text : str
        That line as written (stripped).
    reason : str
        What is wrong, in words.

    Examples
    --------
    >>> str(ProgramError("part.prg", 12, "arc2 (X,Y),1,1", "arc2 needs 3 numbers, got 2"))
    'part.prg:12: arc2 needs 3 numbers, got 2\\n    12 | arc2 (X,Y),1,1'
    """

    def __init__(self, path: str, line: int | None, text: str, reason: str):
        self.path, self.line, self.text, self.reason = str(path), line, text, reason
        super().__init__(self._message())

    def _message(self) -> str:
        if self.line is None:
            return f"{self.path}: {self.reason}"
        text = self.text if len(self.text) <= _SHOWN else self.text[:_SHOWN] + " …"
        return f"{self.path}:{self.line}: {self.reason}\n    {self.line} | {text}"


class ProgramWarning(UserWarning):
    """Something the reader skipped or assumed (one warning per kind, naming a line)."""
