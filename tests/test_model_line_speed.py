"""The output model with the platen speed ν as a known input (model reference §5, §12).

The expected factors are computed here from the constants in data/line_speed.toml, read with
tomllib, not through the model's loader.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from ajtwin._jax import jax, jnp
from ajtwin.model import DigitalModel, coefficient_matrix, load_output_coefficients
from ajtwin.model.calibration import CalibratedCoefficients, Calibration
from ajtwin.model.line_speed import load_line_speed_law
from ajtwin.model.parameters import load_parameters
from ajtwin.model.system import output_function

LAW_FILE = Path(__file__).resolve().parent.parent / "src" / "ajtwin" / "data" / "line_speed.toml"
X = np.array([3.5, 1.0, 0.0, 0.02, 4.6e-7])
U = np.array([375.0, 23.0, 50.0])


@pytest.fixture(scope="module")
def law():
    with LAW_FILE.open("rb") as handle:
        return tomllib.load(handle)["law"]


def test_without_a_speed_the_outputs_are_those_at_the_reference_speed_bit_for_bit(law):
    model = DigitalModel.default()
    xs = X + np.outer(np.linspace(0, 1, 7), [0.3, -0.1, 0.0, 0.05, 1e-7])
    plain = model.outputs(xs, U)
    at_reference = model.outputs(xs, U, np.full(7, law["reference_speed_mm_s"]))
    assert np.array_equal(plain, at_reference)


@pytest.mark.parametrize("speed", [0.5, 1.0, 4.0, 8.0, 19.0])
def test_linewidth_and_overspray_scale_as_the_power_law_and_the_rest_does_not(law, speed):
    model = DigitalModel.default()
    ratio = model.outputs(X, U, speed) / model.outputs(X, U)
    reference = law["reference_speed_mm_s"]
    np.testing.assert_allclose(ratio[0], (reference / speed) ** law["linewidth_exponent"], 1e-14)
    np.testing.assert_allclose(ratio[1], (reference / speed) ** law["overspray_exponent"], 1e-14)
    assert np.array_equal(ratio[2:], np.ones(3))  # pressures and Q_m do not see the speed


def test_outside_its_validity_range_the_law_is_held_at_the_edge(law):
    model = DigitalModel.default()
    base = model.outputs(X, U)[0]
    reference, b = law["reference_speed_mm_s"], law["linewidth_exponent"]
    still = model.outputs(X, U, 0.0)[0] / base  # a dwell with the shutter open: a dot
    fast = model.outputs(X, U, 200.0)[0] / base
    np.testing.assert_allclose(still, (reference / law["min_speed_mm_s"]) ** b, rtol=1e-14)
    np.testing.assert_allclose(fast, (reference / law["max_speed_mm_s"]) ** b, rtol=1e-14)
    with pytest.raises(ValueError, match="platen_speed_mm_s"):
        model.outputs(X, U, -1.0)


def test_the_speed_acts_on_the_calibrated_line(law):
    """A machine's offset widens its line at every speed in proportion (f (g L + o))."""
    params = load_parameters()
    matrix = coefficient_matrix(load_output_coefficients())
    calibration = Calibration(linewidth_gain=0.8, linewidth_offset_um=-20.0)
    nominal = np.asarray(output_function(X, U, params, matrix))
    calibrated = np.asarray(
        output_function(X, U, params, CalibratedCoefficients(matrix, calibration), 5.0)
    )
    factor = (law["reference_speed_mm_s"] / 5.0) ** law["linewidth_exponent"]
    np.testing.assert_allclose(calibrated[0], factor * (0.8 * nominal[0] - 20.0), rtol=1e-13)


def test_the_speed_input_is_differentiable_and_batches(law):
    params = load_parameters()
    matrix = jnp.asarray(coefficient_matrix(load_output_coefficients()))
    speed_law = load_line_speed_law()

    def width(speed):
        return output_function(X, U, params, matrix, speed, speed_law)[0]

    speed = 3.0
    slope = float(jax.grad(width)(speed))
    np.testing.assert_allclose(slope, -law["linewidth_exponent"] * width(speed) / speed, 1e-12)
    speeds = jnp.array([1.0, 2.0, 3.0])
    batched = jax.vmap(width)(speeds)
    np.testing.assert_allclose(batched, [width(s) for s in (1.0, 2.0, 3.0)], rtol=1e-14)
