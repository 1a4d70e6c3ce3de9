"""The reader's memory follows the print's length on the 1 s grid, not the file's size.

A CSV is read in chunks of ``CHUNK_ROWS`` rows and averaged into seconds as it goes, so a
10 Hz log needs memory for its seconds, not its rows; a print longer than
``MAX_RECORD_SECONDS`` is refused where it crosses the limit, before the rest is read.
(The figures on a 1.6 GB file are in docs/reference/record-format.md, "Limits".)
"""

from __future__ import annotations

import tracemalloc
import warnings

import numpy as np
import pandas as pd
import pytest

import ajtwin.io.records as records


def _log(path, n_rows: int, step_s: float) -> int:
    rng = np.random.default_rng(0)
    t = np.round(np.arange(n_rows) * step_s, 3)
    pd.DataFrame(
        {
            "time_s": t,
            "atomizer_current_mA": 375 + rng.normal(0, 1, n_rows),
            "carrier_flow_sccm": 23 + rng.normal(0, 0.1, n_rows),
            "sheath_flow_sccm": 50 + rng.normal(0, 0.1, n_rows),
            "carrier_pressure_Pa": 5661 + rng.normal(0, 6, n_rows),
            "sheath_pressure_Pa": 5641 + rng.normal(0, 6, n_rows),
            "linewidth_um": 43 + rng.normal(0, 2, n_rows),
            "overspray_um": 29 + rng.normal(0, 3, n_rows),
            "material_flow_mL_s": 1.5e-8 * (1 + rng.normal(0, 0.17, n_rows)),
        }
    ).to_csv(path, index=False)
    return n_rows * 9 * 8  # bytes of the rows as float64


def _traced_read(path):
    """(the record, the peak of the memory tracemalloc saw while it was read [bytes])."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tracemalloc.start()
        try:
            record = records.read_record(path)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    return record, peak


def test_reader_memory_follows_the_seconds_not_the_rows(tmp_path, monkeypatch):
    monkeypatch.setattr(records, "CHUNK_ROWS", 5_000, raising=False)
    path = tmp_path / "hz10.csv"
    raw_bytes = _log(path, 300_000, 0.1)  # 30,000 s at 10 Hz
    record, peak = _traced_read(path)
    # e8d5de7 held the whole table and its copies: 34 MB for 14 MB of rows (2.4×)
    assert peak < 0.5 * raw_bytes, f"peak {peak / 1e6:.1f} MB for {raw_bytes / 1e6:.1f} MB of rows"
    assert len(record) == 30_001  # 10 rows per second averaged: seconds 0 … 30,000


def test_a_print_longer_than_the_limit_is_refused_where_it_crosses_it(tmp_path, monkeypatch):
    monkeypatch.setattr("ajtwin.io.table.MAX_RECORD_SECONDS", 1000)
    monkeypatch.setattr(records, "CHUNK_ROWS", 300, raising=False)
    path = tmp_path / "long.csv"
    _log(path, 5_000, 1.0)
    seen = []
    real_push = records.TableBuilder.push

    def counting_push(self, chunk, first_row):
        seen.append(len(chunk))
        return real_push(self, chunk, first_row)

    monkeypatch.setattr(records.TableBuilder, "push", counting_push)
    message = r"row 1002 \(line 1003\), column 'time_s': the print reaches 1001 s .*split the log"
    with pytest.raises(records.RecordError, match=message):
        records.read_record(path)
    assert sum(seen) <= 1200  # the chunks up to the limit, not the 5,000 rows


def test_a_parquet_record_is_held_about_twice_at_most_while_it_is_read(tmp_path):
    """The reader's own arrays (what tracemalloc sees; Arrow's buffers are its pool's): the
    seconds go to disk as the file's pieces come and the table's block is filled from there,
    not concatenated and then copied into the frame (that held a 24-h record 3.3 times, 32 MB
    for 9.7 MB; it is 2.2 times)."""
    path = tmp_path / "day.parquet"
    csv = tmp_path / "rows.csv"
    _log(csv, 40_000, 1.0)
    pd.read_csv(csv).to_parquet(path)
    record, peak = _traced_read(path)
    table = record.data.memory_usage(index=False).sum()
    assert len(record) == 40_000
    assert peak < 2.75 * table, f"peak {peak / 1e6:.1f} MB for a {table / 1e6:.1f} MB table"
