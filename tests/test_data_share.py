"""which states this print's data determined (ΔR_T: the prior's band)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from ajtwin.apps.detection.mismatch import data_share, determined_states, load_guard_settings
from ajtwin.estimation.filters import DEFAULT_SCALING
from ajtwin.model import STATE_NAMES


def test_data_share_by_hand():
    """Scaled coordinates, F = diag(0.5, 1, 1, 1, 1), Q = 0.1, prior 1, posterior P:
    state 0 measured (P 0.2 each step), state 2 never (its P follows the prior recursion).
    Π_0 = 1 → share 0.8; Π_1 = 0.25·1 + 0.1 = 0.35 → 1 − 0.2/0.35 = 0.428571…;
    state 2: Π = P = 1, 1.1 → share 0."""
    s = np.asarray(DEFAULT_SCALING.state, dtype=float)
    outer = np.outer(s, s)
    jac = np.tile(np.diag([0.5, 1.0, 1.0, 1.0, 1.0]), (2, 1, 1))
    post = np.array([np.diag([0.2, 1.0, 1.0, 1.0, 1.0]), np.diag([0.2, 1.1, 1.1, 1.1, 1.1])])
    pred = np.array([np.eye(5), np.diag([0.5**2 * 0.2 + 0.1, 1.1, 1.1, 1.1, 1.1])])
    f = SimpleNamespace(
        covariances=post * outer,  # display units, as the filter returns them
        predicted_covariances=pred * outer,
        transition_jacobians=jac,
    )
    share = data_share(f)
    assert share[0, 0] == pytest.approx(0.8)
    assert share[1, 0] == pytest.approx(1 - 0.2 / 0.35)
    assert share[:, 2] == pytest.approx([0.0, 0.0])
    status = determined_states(share, {"undetermined_share": 0.05})
    assert status["droplet_diameter_um"] == {"data_share": 0.4286, "determined": True}
    assert status["tube_deposition_um"]["determined"] is False


@pytest.fixture(scope="module")
def record():
    from ajtwin.simulation.printer import simulate

    return simulate("exp1", seed=3, duration_min=6.0)


def test_tube_deposition_is_not_determined_and_the_cli_says_so(tmp_path, record):
    from ajtwin.cli.estimate import estimate
    from ajtwin.io.records import write_record

    path = tmp_path / "p.parquet"
    write_record(record, path)
    out = tmp_path / "states.csv"
    res = CliRunner().invoke(estimate, [str(path), "--out", str(out)])
    assert res.exit_code == 0, res.output
    frame = pd.read_csv(out)
    threshold = load_guard_settings()["undetermined_share"]
    end = frame.iloc[-1]
    assert end["data_share_tube_deposition_um"] < threshold
    assert not end["determined_tube_deposition_um"]
    for name in ("droplet_diameter_um", "nozzle_deposition_um"):
        assert end["data_share_" + name] > 0.5 and end["determined_" + name], name
    assert all("determined_" + n in frame for n in STATE_NAMES)
    assert "not determined by this print's data" in res.output
    assert "tube_deposition_um" in res.output.split("not determined by this print's data")[1]


def test_machine_show_names_the_undetermined_state(tmp_path, record):
    from ajtwin.cli.machine import machine
    from ajtwin.engine.ingest import ingest_record
    from ajtwin.store.registry import Registry

    store = tmp_path / "r.sqlite"
    reg = Registry(store)
    reg.add_machine("m")
    result = ingest_record(reg, "m", record)
    shares = result.summary["data_share"]
    assert shares["tube_deposition_um"]["determined"] is False
    assert shares["nozzle_deposition_um"]["determined"] is True
    reg.close()
    res = CliRunner().invoke(machine, ["show", "m", "--store", str(store)])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.output.splitlines() if "not determined" in ln]
    assert len(lines) >= 1 and any(ln.strip().startswith("ΔR_T") for ln in lines)
    assert not any(ln.strip().startswith(("d_a", "ΔR_N")) for ln in lines)
