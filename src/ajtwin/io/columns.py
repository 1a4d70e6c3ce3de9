"""Column names of a log → record columns, with the unit each name carries.

Instrument software names columns its own way and often puts the unit in the name:
``Linewidth [µm]``, ``Carrier Pressure (kPa)``, ``Q_c / sccm``, ``time_ms``. A name is
resolved in three tries:

1. the whole name is an alias (``aliases.toml``, plus the user's alias file): its unit is
   the record column's own;
2. the name is ``base [unit]``, ``base (unit)``, ``base {unit}``, ``base / unit`` or
   ``base in unit``, and ``base`` is an alias (or a column name without its unit);
3. the name ends in ``_unit`` or `` unit`` (``time_ms``, ``carrier_pressure_kPa``).

The unit is looked up in the ``[units]`` table of ``aliases.toml`` (spellings such as
``um``, ``µm``, ``micron``) and must measure the same quantity as the record column's unit;
values are then converted with :func:`ajtwin.units.convert`. A name whose base is a record
column but whose unit is unknown or of another quantity is not used, and when that column
is then missing the error names the column found and what to do. Matching ignores case
and treats runs of blanks, ``_`` and ``-`` alike.

Examples
--------
>>> plan = resolve_columns(["Time [s]", "Carrier Pressure (kPa)", "note"], "log.csv")
>>> [(c.source, c.name, c.unit) for c in plan.columns]
[('Time [s]', 'time_s', 's'), ('Carrier Pressure (kPa)', 'carrier_pressure_Pa', 'kPa'), \
('note', 'note', None)]
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

from ajtwin import units as unit_conversion
from ajtwin.config import packaged_toml, read_toml
from ajtwin.io.schema import UNITS as COLUMN_UNITS

#: How each record column's name ends in its unit (stripped to get the column's base name).
_NAME_SUFFIX = {"s": "_s", "mA": "_mA", "sccm": "_sccm", "Pa": "_Pa", "um": "_um",
                "mL/s": "_mL_s", "mL": "_mL", "mm/s": "_mm_s", "1": ""}  # fmt: skip

_BRACKETED = re.compile(
    r"^(?P<base>.*?\S)\s*(?:\[(?P<a>[^\]]*)\]|\((?P<b>[^)]*)\)|\{(?P<c>[^}]*)\})$"
)
_SLASHED = re.compile(r"^(?P<base>.*?\S)\s+/\s*(?P<unit>\S.*)$")
_IN_UNIT = re.compile(r"^(?P<base>.*?\S)\s+in\s+(?P<unit>\S+)$", re.IGNORECASE)
_SEPARATORS = re.compile(r"[\s_\-]+")


class ColumnError(ValueError):
    """A column name that cannot be used as it is; the message says what to do."""


def normalise_name(name) -> str:
    """Lower case, blanks/``_``/``-`` runs as one blank, stripped: the key names match on."""
    return _SEPARATORS.sub(" ", str(name).strip().lower()).strip()


def _normalise_unit(text: str) -> str:
    return re.sub(r"\s+", "", str(text)).lower()


@dataclass(frozen=True)
class Column:
    """One column of the file: its name there, its record name, and the unit it is in.

    ``name`` is the record column (``known``) or the file's name (an extra column);
    ``unit`` is the unit of the file's values (None: the record column's own, or unknown
    for an extra column).
    """

    source: str
    name: str
    unit: str | None = None
    known: bool = False

    @property
    def converted(self) -> bool:
        """Whether the column is a known one whose values were converted from another unit."""
        return self.known and self.unit is not None and self.unit != COLUMN_UNITS[self.name]


@dataclass
class ColumnPlan:
    """How the columns of one file become record columns (see :func:`resolve_columns`)."""

    columns: list[Column]
    #: names whose base is a record column but whose unit cannot be used: (name, column, why)
    near_misses: list[tuple[str, str, str]] = field(default_factory=list)

    def by_name(self) -> dict[str, Column]:
        """The planned columns by their record name."""
        return {c.name: c for c in self.columns}

    def describe_renames(self) -> str:
        """'a' → 'b' (kPa → Pa), … for the columns that were renamed or converted."""
        parts = []
        for c in self.columns:
            if not c.known or (c.source == c.name and not c.converted):
                continue
            text = f"{c.source!r} → {c.name!r}"
            if c.converted:
                text += f" ({c.unit} → {COLUMN_UNITS[c.name]})"
            parts.append(text)
        return ", ".join(parts)

    def missing_hint(self, missing: list[str]) -> str:
        """What to do about missing record columns: near misses and an alias-file snippet."""
        lines = []
        for name, column, why in self.near_misses:
            if column in missing:
                lines.append(f"column {name!r} looks like {column!r} but {why}")
        unused = [c for c in self.columns if not c.known]
        suggestions = {}
        for column in missing:
            wanted = unit_conversion.dimension(COLUMN_UNITS[column])
            for c in unused:
                if c.unit is not None and unit_conversion.dimension(c.unit) == wanted:
                    suggestions.setdefault(column, []).append(c.source)
        if suggestions:
            lines.append(
                "columns in a unit of the right kind: "
                + "; ".join(f"{k}: {', '.join(map(repr, v))}" for k, v in suggestions.items())
                + ". If one of them is it, put its name in an alias file and pass it with "
                "--aliases FILE (read_record(path, aliases=FILE)):\n  [aliases]\n"
                + "\n".join(
                    f"  {k} = [{_toml_string(_base_of(v[0]))}]" for k, v in suggestions.items()
                )
            )
        return "\n".join(lines)


def _toml_string(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _base_of(name: str) -> str:
    for pattern in (_BRACKETED, _SLASHED, _IN_UNIT):
        match = pattern.match(str(name).strip())
        if match:
            return match.group("base")
    return str(name).strip()


@lru_cache(maxsize=1)
def _packaged_tables() -> tuple[dict, dict]:
    table = packaged_toml("io/aliases.toml")
    return table.get("aliases", {}), table.get("units", {})


@lru_cache(maxsize=1)
def unit_spellings() -> dict[str, str]:
    """Normalised spelling → unit of :mod:`ajtwin.units` (from ``[units]`` of aliases.toml)."""
    _, table = _packaged_tables()
    mapping: dict[str, str] = {}
    for unit, spellings in table.items():
        if unit_conversion.dimension(unit) is None:
            raise ValueError(f"aliases.toml: [units] names {unit!r}, which ajtwin.units lacks")
        for spelling in [unit, *spellings]:
            key = _normalise_unit(spelling)
            if mapping.get(key, unit) != unit:
                raise ValueError(
                    f"aliases.toml: unit spelling {spelling!r} means both {mapping[key]!r} "
                    f"and {unit!r}"
                )
            mapping[key] = unit
    return mapping


def parse_unit(text: str) -> str | None:
    """The unit of :mod:`ajtwin.units` a spelling means (``"µm"`` → ``"um"``), or None."""
    spellings = unit_spellings()
    key = _normalise_unit(text)
    if key in spellings:
        return spellings[key]
    if "_" in key:  # "mL_s" in a name like material_flow_mL_s
        return spellings.get(key.replace("_", "/"))
    return None


def alias_tables(path: str | Path | None = None) -> list[dict]:
    """The ``[aliases]`` tables: the packaged one, then the user's file (if any)."""
    tables = [_packaged_tables()[0]]
    if path is not None:
        table = read_toml(path, what="alias")
        aliases = table.get("aliases", {})
        if not isinstance(aliases, dict):
            raise ValueError(f"alias file {path}: [aliases] must be a table")
        tables.append(aliases)
    for aliases in tables:
        for canonical, names in aliases.items():
            if canonical not in COLUMN_UNITS:
                raise ValueError(
                    f"alias file names unknown column {canonical!r}; known: "
                    f"{', '.join(COLUMN_UNITS)}"
                )
            if not isinstance(names, list):
                raise ValueError(f"alias file {path}: aliases.{canonical} must be a list of names")
    return tables


def name_tables(path: str | Path | None = None) -> tuple[dict[str, str], dict[str, str]]:
    """(whole-name key → column, base-name key → column) from the alias tables."""
    whole: dict[str, str] = {}
    base: dict[str, str] = {}
    for column, unit in COLUMN_UNITS.items():
        whole[normalise_name(column)] = column
        suffix = _NAME_SUFFIX[unit]
        stem = column[: len(column) - len(suffix)] if suffix else column
        base[normalise_name(stem)] = column
    for aliases in alias_tables(path):
        for column, names in aliases.items():
            for name in names:
                whole[normalise_name(name)] = column
                stem = _base_of(str(name))
                base.setdefault(normalise_name(stem), column)
                base.setdefault(normalise_name(name), column)
    return whole, base


def _split_unit(name: str):
    """(base, unit text) candidates of a name that may carry a unit, most explicit first."""
    text = str(name).strip()
    match = _BRACKETED.match(text)
    if match:
        unit = next(g for g in match.group("a", "b", "c") if g is not None)
        yield match.group("base"), unit, True
        return
    for pattern in (_SLASHED, _IN_UNIT):
        match = pattern.match(text)
        if match:
            yield match.group("base"), match.group("unit"), True
            return
    # a trailing _unit / " unit": the last one or two parts (mL_s)
    parts = re.split(r"([_\s]+)", text)
    for n_parts in (1, 2):
        cut = 2 * n_parts
        if len(parts) > cut:
            yield "".join(parts[:-cut]), "".join(parts[-(cut - 1) :]), False


def resolve_columns(
    names, where: str = "<record>", aliases: str | Path | None = None
) -> ColumnPlan:
    """Map a file's column names to record columns and units (see the module doc).

    Raises
    ------
    ColumnError
        Two columns that mean the same record column (both are named).
    """
    whole, base = name_tables(aliases)
    plan = ColumnPlan([])
    seen: dict[str, str] = {}
    for source in names:
        source = str(source)
        column = whole.get(normalise_name(source))
        unit = COLUMN_UNITS.get(column) if column else None
        if column is None:
            for stem, unit_text, explicit in _split_unit(source):
                candidate = base.get(normalise_name(stem))
                if candidate is None:
                    continue
                parsed = parse_unit(unit_text)
                own = COLUMN_UNITS[candidate]
                if parsed is None:
                    if explicit:
                        plan.near_misses.append(
                            (source, candidate, f"{unit_text.strip()!r} is not a unit ajtwin "
                             f"reads; convert the column to {own} or name its unit as one of: "
                             f"{', '.join(_spellings_of_dimension(own))}")
                        )  # fmt: skip
                    continue
                if unit_conversion.dimension(parsed) != unit_conversion.dimension(own):
                    plan.near_misses.append(
                        (source, candidate, f"its unit {unit_text.strip()!r} is a "
                         f"{unit_conversion.dimension(parsed)}, not a "
                         f"{unit_conversion.dimension(own)} like {own}")
                    )  # fmt: skip
                    continue
                column, unit = candidate, parsed
                break
        if column is None:
            extra_unit = None
            for _, unit_text, explicit in _split_unit(source):
                if explicit:
                    extra_unit = parse_unit(unit_text)
                break
            plan.columns.append(Column(source, source, extra_unit, known=False))
            continue
        if column in seen:
            raise ColumnError(
                f"{where}: columns {seen[column]!r} and {source!r} both mean {column!r}"
            )
        seen[column] = source
        plan.columns.append(Column(source, column, unit, known=True))
    return plan


def _spellings_of_dimension(unit: str) -> list[str]:
    wanted = unit_conversion.dimension(unit)
    _, table = _packaged_tables()
    return [u for u in table if unit_conversion.dimension(u) == wanted]


def convert_values(values, column: Column):
    """A known column's values (float array) in the record column's own unit."""
    if not column.converted:
        return values
    return unit_conversion.convert(values, column.unit, COLUMN_UNITS[column.name])
