"""CSV dialects of real exports: separator, decimal mark, thousands grouping.

A spreadsheet in a European locale saves ``;``-separated text with decimal commas and
``.`` grouping thousands (``5.741,6``), often with a byte-order mark and CRLF line ends;
instrument software writes tab-separated ``.tsv``/``.txt``. :func:`sniff_dialect` finds the
separator and the decimal mark from the first lines of a file; :data:`DIALECTS` names the
dialects a user can give instead (``--csv-dialect``).

The separator: :class:`csv.Sniffer` proposes one of ``, ; TAB |``; it is taken when it
splits the header into at least two fields and every sampled line into as many. (Sniffer
alone is not enough: on a ``;`` file with decimal commas it can pick ``,``, which appears
as regularly.) When Sniffer fails, the one candidate that splits consistently is taken;
if several do, the choice is reported as assumed.

The decimal mark: cells that can only be read one way vote — ``2,5``, ``0,000``,
``8,4e-09``, ``5.741,6`` for a comma; ``2.5``, ``1.5e-08``, ``5,741.6`` for a point.
``5,741`` or ``5.741`` (one to three digits, a mark, three digits) could be either and
do not vote. No vote at all: a decimal point is assumed and, when such ambiguous cells
exist, reported as assumed. Thousands groups are accepted only as whole groups of three
digits (pandas' own ``thousands=`` reads ``1.5`` as 15 in a decimal-comma file, so
numbers in a non-default dialect are checked against :func:`number_pattern` first).

Examples
--------
>>> d = sniff_dialect(["time_s;linewidth_um", "0,0;43,25", "1,0;44,1"])
>>> d.delimiter, d.decimal, d.describe()
(';', ',', "';'-separated, decimal comma, '.' between thousands")
>>> import pandas as pd
>>> parse_numbers(pd.Series(["5.741,6", "2,5", "1.5"], dtype="string"), d).tolist()
[5741.6, 2.5, nan]
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

#: Separators tried, in order of preference when the evidence is equal.
CANDIDATE_DELIMITERS = (",", ";", "\t", "|")
_DELIMITER_NAMES = {",": "comma", ";": "semicolon", "\t": "tab", "|": "pipe"}
#: Blanks that group thousands in some locales (space, no-break space, narrow no-break space).
_BLANK_GROUPING = (" ", "\u00a0", "\u202f")
#: Lines read to detect the dialect.
SNIFF_LINES = 200


@dataclass(frozen=True)
class CsvDialect:
    """How a delimited text file writes its table.

    Parameters
    ----------
    delimiter : str
        Field separator: ``,``, ``;``, tab or ``|``.
    decimal : str
        Decimal mark: ``.`` or ``,``.
    detected : bool
        Found by :func:`sniff_dialect` (False: given by the user, or the default).
    assumed : tuple of str
        What detection had to assume (the file was ambiguous), as sentences.
    """

    delimiter: str = ","
    decimal: str = "."
    detected: bool = False
    assumed: tuple[str, ...] = field(default_factory=tuple)

    @property
    def thousands(self) -> tuple[str, ...]:
        """Characters accepted between groups of three digits."""
        other = "." if self.decimal == "," else ","
        marks = (other,) if other != self.delimiter else ()
        return marks + tuple(b for b in _BLANK_GROUPING if b != self.delimiter)

    @property
    def is_default(self) -> bool:
        """Plain CSV: ``,``-separated, decimal point (what pandas reads without options)."""
        return self.delimiter == "," and self.decimal == "."

    @property
    def name(self) -> str:
        """The dialect's ``--csv-dialect`` name (``semicolon-decimal-comma``, ...)."""
        base = _DELIMITER_NAMES[self.delimiter]
        return base + ("-decimal-comma" if self.decimal == "," else "")

    def describe(self) -> str:
        """The dialect in words, for the warning that says how a file was read."""
        sep = "tab" if self.delimiter == "\t" else repr(self.delimiter)
        text = f"{sep}-separated, decimal {'comma' if self.decimal == ',' else 'point'}"
        other = "." if self.decimal == "," else ","
        if other in self.thousands:
            text += f", {other!r} between thousands"
        return text


#: Dialects by the name ``--csv-dialect`` takes ("auto" = detect).
DIALECTS = {
    CsvDialect(d, m).name: CsvDialect(d, m) for d in CANDIDATE_DELIMITERS for m in (".", ",")
}
DIALECT_CHOICES = ("auto", *DIALECTS)


def dialect_from_name(name: str | CsvDialect | None) -> CsvDialect | None:
    """A :class:`CsvDialect` from its name (None or ``"auto"``: detect)."""
    if name is None or isinstance(name, CsvDialect):
        return name
    key = str(name).strip().lower()
    if key == "auto":
        return None
    if key not in DIALECTS:
        raise ValueError(f"unknown CSV dialect {name!r}; use one of: {', '.join(DIALECT_CHOICES)}")
    return DIALECTS[key]


# --------------------------------------------------------------------------- #
# Detection
# --------------------------------------------------------------------------- #
_EXP = r"(?:[eE][+-]?\d+)"
# cells only one reading fits (see the module doc)
_COMMA_DECIMAL = re.compile(
    rf"^[+-]?(?:\d{{1,3}}(?:\.\d{{3}})+,\d*{_EXP}?|\d+,\d+{_EXP}|0,\d+|\d{{4,}},\d+|\d+,\d{{1,2}}|\d+,\d{{4,}}|,\d+)$"
)
_POINT_DECIMAL = re.compile(
    rf"^[+-]?(?:\d{{1,3}}(?:,\d{{3}})+\.\d*{_EXP}?|\d+\.\d+{_EXP}|0\.\d+|\d{{4,}}\.\d+|\d+\.\d{{1,2}}|\d+\.\d{{4,}}|\.\d+)$"
)
_EITHER = re.compile(r"^[+-]?\d{1,3}[.,]\d{3}$")


def _split(lines: list[str], delimiter: str) -> list[list[str]]:
    return [row for row in csv.reader(lines, delimiter=delimiter, quotechar='"')]


def _consistent(rows: list[list[str]]) -> bool:
    width = len(rows[0]) if rows else 0
    return width >= 2 and all(len(r) == width for r in rows[1:] if r)


def sniff_dialect(lines: list[str]) -> CsvDialect:
    """The dialect of a table from its header line and first data lines (see module doc).

    Parameters
    ----------
    lines : list of str
        The column-name line then data lines, without comment lines or line ends. A last
        line that may be cut should be left out.
    """
    lines = [line for line in lines[: SNIFF_LINES + 1] if line.strip()]
    if not lines:
        return CsvDialect(detected=True)
    assumed: list[str] = []
    split = {d: _split(lines, d) for d in CANDIDATE_DELIMITERS}
    consistent = [d for d in CANDIDATE_DELIMITERS if _consistent(split[d])]
    try:
        proposed = csv.Sniffer().sniff("\n".join(lines), delimiters="".join(CANDIDATE_DELIMITERS))
        proposed = proposed.delimiter
    except csv.Error:
        proposed = None
    if proposed in consistent:
        delimiter = proposed
    elif len(consistent) == 1:
        delimiter = consistent[0]
    elif consistent:
        delimiter = consistent[0]
        assumed.append(
            f"the lines split evenly at {' and at '.join(map(_shown, consistent))}; "
            f"assumed {_shown(delimiter)}"
        )
    else:
        # no separator splits every line alike: take the one that splits the header most
        # (the table reader then names the line that does not fit)
        delimiter = max(CANDIDATE_DELIMITERS, key=lambda d: len(split[d][0]))
        if len(split[delimiter][0]) < 2:
            delimiter = ","
    rows = split[delimiter][1:]
    cells = [cell.strip() for row in rows for cell in row]
    comma = sum(1 for c in cells if _COMMA_DECIMAL.match(c))
    point = sum(1 for c in cells if _POINT_DECIMAL.match(c))
    either = sum(1 for c in cells if _EITHER.match(c))
    if comma and point:
        decimal = "," if comma > point else "."
        assumed.append(
            f"{comma} value(s) have a decimal comma and {point} a decimal point; assumed "
            f"the {'comma' if decimal == ',' else 'point'} (the others cannot be read)"
        )
    elif comma:
        decimal = ","
    else:
        decimal = "."
        if either and not point:
            assumed.append(
                f"no value shows the decimal mark unambiguously ({either} like "
                f"{next(c for c in cells if _EITHER.match(c))!r}); assumed a decimal point"
            )
    return CsvDialect(delimiter, decimal, detected=True, assumed=tuple(assumed))


def _shown(delimiter: str) -> str:
    return "tab" if delimiter == "\t" else repr(delimiter)


# --------------------------------------------------------------------------- #
# Numbers
# --------------------------------------------------------------------------- #
def number_pattern(dialect: CsvDialect) -> re.Pattern:
    """A cell that is a number in ``dialect``: optional sign, whole groups of three digits
    between thousands marks (or plain digits), decimal mark, exponent; or inf/nan."""
    d = re.escape(dialect.decimal)
    groups = "".join(re.escape(t) for t in dialect.thousands)
    grouped = rf"\d{{1,3}}(?:[{groups}]\d{{3}})+" if groups else r"(?!)"
    return re.compile(
        rf"[+-]?(?:(?:{grouped}|\d+)(?:{d}\d*)?|{d}\d+)(?:[eE][+-]?\d+)?"
        r"|[+-]?(?:inf|infinity|nan)",
        re.IGNORECASE,
    )


def parse_numbers(text: pd.Series, dialect: CsvDialect) -> pd.Series:
    """Cells (text) → float, NaN where a cell is not a number in ``dialect``.

    The caller tells a blank cell (missing) from one that is not a number.
    """
    if dialect.is_default:
        return pd.to_numeric(text, errors="coerce").astype(float)
    text = text.astype("string").str.strip()
    ok = text.str.fullmatch(number_pattern(dialect)).fillna(False).to_numpy(dtype=bool)
    plain = text.where(ok)
    for mark in dialect.thousands:
        plain = plain.str.replace(mark, "", regex=False)
    if dialect.decimal != ".":
        plain = plain.str.replace(dialect.decimal, ".", regex=False)
    numbers = pd.to_numeric(plain, errors="coerce").astype(float)
    return numbers.where(ok, np.nan)
