"""Physical state ranges (data/state_limits.toml via ajtwin.model.limits)."""

import numpy as np
import pytest

from ajtwin.model import load_parameters
from ajtwin.model.limits import StateLimits

NOMINAL = np.array([3.5, 1.0, 0.0, 0.03, 4.6e-7])


@pytest.fixture(scope="module")
def limits():
    return StateLimits.load(load_parameters())


def test_nominal_state_is_physical(limits):
    assert limits.violations(NOMINAL) == []
    assert limits.inside(NOMINAL).all()


def test_bounds_resolved_against_geometry(limits):
    # V_l up to the 3 mL vial; deposits up to the tube (789 µm) and nozzle (75 µm) radius
    assert limits.upper[1] == pytest.approx(3.0)
    assert limits.upper[2] == pytest.approx(789.0)
    assert limits.upper[3] == pytest.approx(75.0)
    assert limits.lower[3] == pytest.approx(-0.05 * 75.0)


@pytest.mark.parametrize(
    ("index", "value", "name"),
    [
        (0, 534.0, "droplet_diameter_um"),  # a 534 µm droplet
        (0, -1.07, "droplet_diameter_um"),
        (1, -2.35, "vial_volume_mL"),
        (1, 0.0, "vial_volume_mL"),  # an empty vial is no state to print from
        (3, 80.0, "nozzle_deposition_um"),
        (4, -1.4e-6, "aerosol_fraction"),
        (4, np.nan, "aerosol_fraction"),
    ],
)
def test_impossible_states_are_named(limits, index, value, name):
    x = NOMINAL.copy()
    x[index] = value
    messages = limits.violations(x)
    assert len(messages) == 1 and messages[0].startswith(name)


def test_first_violation_index(limits):
    means = np.tile(NOMINAL, (6, 1))
    assert limits.first_violation_index(means) is None
    means[4, 1] = -0.1
    means[5, 0] = 100.0
    assert limits.first_violation_index(means) == 4
