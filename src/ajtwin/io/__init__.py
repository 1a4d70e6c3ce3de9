"""ajtwin.io — print records (machine logs and virtual prints), see
docs/reference/record-format.md."""

from ajtwin.io.records import (
    DEFAULT_META,
    INPUT_COLUMNS,
    OUTPUT_COLUMNS,
    RECORD_COLUMNS,
    TRUTH_COLUMNS,
    UNITS,
    PrintRecord,
    RecordError,
    read_record,
    write_record,
)

__all__ = [
    "PrintRecord",
    "RecordError",
    "read_record",
    "write_record",
    "DEFAULT_META",
    "INPUT_COLUMNS",
    "OUTPUT_COLUMNS",
    "RECORD_COLUMNS",
    "TRUTH_COLUMNS",
    "UNITS",
]
