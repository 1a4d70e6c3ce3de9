"""``ajtwin estimate`` writes its table a chunk of the run at a time: the same table, guard
and data share as from the whole run held at once, which it no longer keeps."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from ajtwin.engine.estimate import estimate_to_csv
from ajtwin.estimation import Twin
from ajtwin.simulation import simulate


@pytest.fixture(scope="module")
def record():
    # 25 min: EM at 120, 300, 600, … s, so the run comes in several chunks
    return simulate("exp1", seed=2, duration_min=25)


@pytest.mark.parametrize("aerosol_level_std", [0.0, 0.35])
def test_the_table_in_chunks_is_the_table_of_the_whole_run(tmp_path, record, aerosol_level_std):
    """Also with φ_A's level unknown (its band carries the vial's drain from chunk to chunk)."""
    chunks, whole = [], None
    twin = Twin.default(aerosol_level_std=aerosol_level_std)
    real_run = Twin.run

    def counting_run(self, *args, sink=None, **kwargs):
        if sink is None:
            return real_run(self, *args, **kwargs)

        def counted(first, chunk):
            chunks.append(first)
            sink(first, chunk)

        return real_run(self, *args, sink=counted, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Twin, "run", counting_run)
        parts = estimate_to_csv(twin, record, tmp_path / "parts.csv")
    whole = estimate_to_csv(
        Twin.default(aerosol_level_std=aerosol_level_std),
        record,
        tmp_path / "whole.csv",
        whole=True,
    )
    assert len(chunks) >= 4 and chunks[0] == 0
    # the rows waited on disk beside the output, and are gone
    assert sorted(p.name for p in tmp_path.iterdir()) == ["parts.csv", "whole.csv"]
    a, b = pd.read_csv(tmp_path / "parts.csv"), pd.read_csv(tmp_path / "whole.csv")
    assert list(a.columns) == list(b.columns)
    assert len(a) == len(b) == parts.rows == whole.rows == len(record)
    for column in a.columns:
        if a[column].dtype == object or a[column].dtype == bool:
            assert (a[column].astype(str) == b[column].astype(str)).all(), column
        else:
            np.testing.assert_allclose(a[column], b[column], rtol=1e-9, atol=1e-12, err_msg=column)
    assert parts.mismatch.mismatch == whole.mismatch.mismatch
    assert parts.mean_nis_per_output == pytest.approx(whole.mean_nis_per_output, rel=1e-9)
    assert parts.undetermined == whole.undetermined
    assert parts.reinitialised == whole.reinitialised
    # the run it returns keeps the print's end, not its steps
    np.testing.assert_allclose(parts.run.end_mean, whole.run.end_mean, rtol=1e-12)
    assert len(parts.run.filtered.means) < len(record)
